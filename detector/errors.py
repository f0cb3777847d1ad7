"""The one exception type for errors a user can cause in ``detector`` (bad files, bad options, bad checkpoints).

The CLI turns it (and ``argen.errors.ArgenError`` raised by ``argen.h5``) into one line on stderr and
exit code 2; anything else is a bug and raises normally.
"""


class DetectorError(Exception):
    """A problem with the user's input: a malformed label file, a mismatched checkpoint, a bad option."""

    def __init__(self, message: str = ""):
        # always one line: a path or a value in the message may itself hold line breaks
        super().__init__(str(message).replace("\r", "\\r").replace("\n", "\\n"))
