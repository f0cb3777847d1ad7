"""The one exception type for errors a user can cause (bad files, bad options).

The CLI turns it into one line on stderr and exit code 2; anything else is a bug and raises normally.
"""


class ArgenError(Exception):
    """A problem with the user's input: missing/corrupt files, wrong units, bad options."""
