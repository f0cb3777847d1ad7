"""What the ``detector`` commands share: the error wrapper (user errors, argen's included, become one line on
stderr and exit 2), and the run-folder check."""

from __future__ import annotations

import functools
import shutil
from pathlib import Path

import typer

from detector.errors import DetectorError, argen_errors

#: Files that mark a folder as a training run (``--overwrite`` removes only such folders).
RUN_MARKERS = ("config.yaml", "metrics.csv", "last.pt", "two_stage.yaml")

#: The default --preset: the two-stage detector (detector.two_stage); "cpu" and "paper" are the paper's network.
TWO_STAGE = "two-stage"


def fail(msg: str, code: int = 2) -> None:
    """Print one line ``detector: error: MSG`` on stderr and exit with ``code``."""
    typer.echo(f"detector: error: {msg}", err=True)
    raise typer.Exit(code)


def user_errors(fn):
    """Turn DetectorError (and argen's errors, through :func:`detector.errors.argen_errors`) into one line and
    exit 2; Ctrl-C into a hint and exit 130."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            with argen_errors():
                return fn(*args, **kwargs)
        except KeyboardInterrupt:
            fail("interrupted; add --resume to continue from the last checkpoint", 130)
        except DetectorError as exc:
            fail(str(exc))

    return wrapper


def prepare_run_folder(out: Path, resume: bool, overwrite: bool) -> None:
    """Refuse to train into an existing run without --resume or --overwrite; --overwrite clears a run folder."""
    if resume or not out.exists() or (out.is_dir() and not any(out.iterdir())):
        return
    if not out.is_dir():
        raise DetectorError(f"--out {out} exists and is not a folder")
    if not overwrite:
        raise DetectorError(f"run folder {out} already exists; add --resume to continue it or --overwrite to replace it")
    if not any((out / m).exists() for m in RUN_MARKERS):
        raise DetectorError(f"--overwrite: {out} does not look like a run folder; not removing it")
    shutil.rmtree(out)
