"""The one exception type for errors a user can cause in ``detector`` (bad files, bad options, bad checkpoints).

The CLI turns it into one line on stderr and exit code 2; anything else is a bug and raises normally. argen's
own user errors (``argen.errors.ArgenError``, from reading a label file, a BOP frame or a camera.json through
argen's data modules) become a DetectorError here, in :func:`argen_errors`, and nowhere else.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from argen.errors import ArgenError


class DetectorError(Exception):
    """A problem with the user's input: a malformed label file, a mismatched checkpoint, a bad option."""

    def __init__(self, message: str = ""):
        # always one line: a path or a value in the message may itself hold line breaks
        super().__init__(str(message).replace("\r", "\\r").replace("\n", "\\n"))


@contextlib.contextmanager
def argen_errors() -> Iterator[None]:
    """Re-raise argen's ArgenError (a missing, truncated or foreign file read through argen) as a DetectorError."""
    try:
        yield
    except ArgenError as exc:
        raise DetectorError(str(exc)) from None
