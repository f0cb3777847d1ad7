"""Nothing lost: capture-sim killed with SIGKILL or stopped by a full disk resumes to the same output.

These run the real `argen` console script in a subprocess, so the kill and the file-size limit hit the
process exactly as they would hit a user's run.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ARGEN = [sys.executable, "-m", "argen.cli.app"]
ARGS = ["capture-sim", "--frames", "5", "--seed", "11", "--quiet",
        "--set", "camera.elevation_deg=[30.0,80.0]"]


def argen(*args, preexec_fn=None) -> subprocess.CompletedProcess:
    return subprocess.run([*ARGEN, *args], capture_output=True, text=True, preexec_fn=preexec_fn, timeout=300)


def files_of(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def log_without_timing(root: Path) -> list[dict]:
    frames = json.loads((root / "capture_log.json").read_text())["frames"]
    return [{k: v for k, v in f.items() if "time" not in k and k != "seconds"} for f in frames]


def same_dataset(a: Path, b: Path) -> None:
    fa, fb = files_of(a), files_of(b)
    assert fa.keys() == fb.keys()
    differing = [k for k in fa if fa[k] != fb[k] and k not in ("capture_log.json", "argen.json")]
    assert not differing
    assert log_without_timing(a) == log_without_timing(b)


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ref") / "ds"
    r = argen(*ARGS, "--out", str(out))
    assert r.returncode == 0, r.stderr
    return out


def test_sigkill_at_any_moment_then_rerun_gives_the_same_dataset(reference, tmp_path):
    for attempt in range(3):
        out = tmp_path / f"ds{attempt}"
        proc = subprocess.Popen([*ARGEN, *ARGS, "--out", str(out)], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 120
        depth = out / "train_pbr" / "000000" / "depth"
        while time.monotonic() < deadline and proc.poll() is None and len(list(depth.glob("*.png"))) < 2:
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        if proc.returncode == -signal.SIGKILL:
            break  # really interrupted (else it finished first: try again)
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "capture_log.json").exists() or log_without_timing(out) != log_without_timing(reference)
    r = argen(*ARGS, "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert not list(out.rglob(".tmp-*"))
    same_dataset(reference, out)


def test_rerun_removes_the_temporary_files_a_killed_run_left(reference, tmp_path):
    # a SIGKILL between mkstemp and the rename leaves a .tmp-* file; the test above only hits that window
    # by chance, so plant the files such a kill leaves and check that the resumed run clears them
    out = tmp_path / "ds"
    shutil.copytree(reference, out)
    rgb = out / "train_pbr" / "000000" / "rgb"
    strays = [rgb / ".tmp-000001-x1y2z3.jpg", out / ".tmp-capture_log-abc.json", out / "models" / ".tmp-obj_000001-q.ply"]
    for p in strays:
        p.write_bytes(b"half")
    keep = out / "notes.tmp-keep"  # not a temporary of ours
    keep.write_text("mine")
    r = argen(*ARGS, "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert not any(p.exists() for p in strays)
    assert keep.read_text() == "mine"
    keep.unlink()
    same_dataset(reference, out)


def _file_size_limit(limit: int):
    def pre():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write then fails with EFBIG, like a full disk
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return pre


def test_full_disk_is_one_line_keeps_what_was_written_and_resumes(reference, tmp_path):
    out = tmp_path / "ds"
    r = argen(*ARGS, "--out", str(out), preexec_fn=_file_size_limit(150_000))
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("argen: error:") and "limit" in lines[0], r.stderr
    for p in out.rglob("*.json"):  # every JSON already there is complete
        json.loads(p.read_text())
    assert not list(out.rglob(".tmp-*"))
    r = argen(*ARGS, "--out", str(out))
    assert r.returncode == 0, r.stderr
    same_dataset(reference, out)


def test_output_that_cannot_be_made_is_one_line(tmp_path):
    """An output folder whose parent is a file: nobody can make it, root included (CI runs as root, which
    permissions do not stop)."""
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    r = argen(*ARGS, "--out", str(blocker / "ds"))
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("argen: error:"), r.stderr
    assert str(blocker / "ds") in lines[0] and "not a directory" in lines[0]
    assert blocker.read_text() == "x"


def test_unreadable_input_file_is_one_line(reference, tmp_path):
    """A scene file that is a FIFO (no one, root included, can read a JSON from it, and reading must not
    block on it) or a folder: one line naming it."""
    for make in (os.mkfifo, os.mkdir):
        ds = tmp_path / make.__name__
        shutil.copytree(reference, ds)
        gt = ds / "train_pbr" / "000000" / "scene_gt.json"
        gt.unlink()
        make(gt)
        r = argen("label", str(ds), "--out", str(tmp_path / f"{make.__name__}.h5"), "--quiet")
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("argen: error:"), r.stderr
        assert str(gt) in lines[0]


@pytest.mark.parametrize("args, msg", [
    (["--frames", "-3"], "--frames must be at least 1"),
    (["--objects", ","], "--objects names no object"),
    (["--set", "placement.objects_per_frame=[0,0]"], "objects_per_frame"),
    (["--set", "board.marker_size=0.01"], "impossible placement"),
    (["--workers", "0"], "--workers must be at least 1"),
    (["--set", "camera.fx=-5"], "fx"),
    (["--set", "noise"], "KEY=VALUE"),
])
def test_out_of_range_options(tmp_path, args, msg):
    from typer.testing import CliRunner

    from argen.cli.app import app

    res = CliRunner().invoke(app, ["capture-sim", "--out", str(tmp_path / "o"), "--quiet", *args])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 2 and len(lines) == 1 and msg in lines[0], res.output
    assert not (tmp_path / "o").exists()


def test_empty_models_folder(tmp_path):
    (tmp_path / "models").mkdir()
    r = argen("capture-sim", "--out", str(tmp_path / "o"), "--models", str(tmp_path / "models"), "--quiet")
    assert r.returncode == 2 and r.stderr.startswith("argen: error:") and len(r.stderr.strip().splitlines()) == 1
