"""The one exception type for errors a user can cause (bad files, bad options).

The CLI turns it into one line on stderr and exit code 2; anything else is a bug and raises normally.
"""


class ArgenError(Exception):
    """A problem with the user's input: missing/corrupt files, wrong units, bad options."""

    def __init__(self, message: str = ""):
        # always one line: a file name, JSON key or YAML value may itself hold line breaks
        super().__init__(str(message).replace("\r", "\\r").replace("\n", "\\n"))
