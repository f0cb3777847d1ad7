"""Atomic file writes: write to a temporary name in the same folder, then rename.

A reader never sees a half-written file; a killed process leaves at most a stray ``.tmp-*`` file.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

from argen.errors import ArgenError


def _file_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _file_mode()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    The temporary name keeps the suffix so that writers choosing a format by extension
    (cv2.imwrite, h5py) still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".tmp-{path.stem}-", suffix=path.suffix, dir=path.parent)
    os.fchmod(fd, _FILE_MODE)  # mkstemp makes 0600 files; give the final file the usual mode
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except OSError as exc:
        tmp_path.unlink(missing_ok=True)
        raise _os_error(exc, path) from exc
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def remove_stray_temps(root: str | os.PathLike) -> int:
    """Delete the ``.tmp-*`` files that a killed writer left anywhere under ``root``; returns how many.

    Only for a folder that one process owns (a resumed capture's output), never while another writes there.
    """
    n = 0
    for p in Path(root).rglob(".tmp-*"):
        if p.is_file():
            p.unlink(missing_ok=True)
            n += 1
    return n


def _os_error(exc: OSError, path: Path) -> ArgenError:
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        why = "file size limit reached" if exc.errno == errno.EFBIG else "disk full"
        return ArgenError(f"{why} while writing {path}; the files already written are intact")
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return ArgenError(f"no permission to write {path}")
    return ArgenError(f"cannot write {path}: {exc.strerror or exc}")


def write_bytes(path: str | os.PathLike, data: bytes, sync: bool = True) -> None:
    """Write ``data`` to ``path`` atomically; ``sync`` also flushes it to the disk before the rename."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            if sync:
                os.fsync(f.fileno())


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> None:
    """Write ``obj`` as JSON to ``path`` atomically."""
    write_bytes(path, (json.dumps(obj, indent=indent, sort_keys=False) + "\n").encode())


def read_json(path: str | os.PathLike, what: str = "JSON file") -> Any:
    """Read a JSON file; a missing or corrupt file is an ArgenError naming it."""
    path = Path(path)
    if not path.is_file():
        raise ArgenError(f"{what} not found: {path}")
    try:
        with open(path) as f:
            return json.load(f)
    except json.JSONDecodeError as exc:
        raise ArgenError(f"{what} {path} is not valid JSON (line {exc.lineno}: {exc.msg})") from exc
    except UnicodeDecodeError as exc:
        raise ArgenError(f"{what} {path} is not a text file") from exc
