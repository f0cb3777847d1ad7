"""The pinned install: what is installed is what lock/py3.X.txt says (when this Python has a lock)."""

import sys
from importlib import metadata
from pathlib import Path

import pytest

LOCK_DIR = Path(__file__).resolve().parents[1] / "lock"
PYVER = f"{sys.version_info[0]}.{sys.version_info[1]}"


def read_pins(path: Path) -> dict[str, str]:
    """{normalised name: version} of a pip constraints file (comments and blank lines skipped)."""
    pins = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, _, version = line.partition("==")
            assert version, f"{path}: '{line}' is not pinned with =="
            pins[name.strip().lower().replace("_", "-")] = version.strip()
    return pins


def test_lock_files_pin_every_line_and_agree_on_torch():
    locks = sorted(LOCK_DIR.glob("py3.*.txt"))
    assert any(p.name == "py3.11.txt" for p in locks)
    for p in locks:
        pins = read_pins(p)
        if not p.name.endswith("-nodeps.txt"):
            assert pins["torch"] == "2.13.0" and "pyrender" in pins and "pyopengl" not in pins
            assert {"numpy", "scipy", "open3d-cpu", "opencv-contrib-python-headless", "trimesh", "h5py", "pip",
                    "setuptools"} <= set(pins)


@pytest.mark.skipif(not (LOCK_DIR / f"py{PYVER}.txt").exists(), reason=f"no lock for Python {PYVER}")
def test_installed_versions_are_the_pinned_ones():
    pins = read_pins(LOCK_DIR / f"py{PYVER}.txt") | read_pins(LOCK_DIR / f"py{PYVER}-nodeps.txt")
    wrong = []
    for name, version in pins.items():
        try:
            have = metadata.version(name)
        except metadata.PackageNotFoundError:
            have = "missing"  # the lock pins what this Python installs: a package it lacks is a broken install
        if have.split("+")[0] != version:
            wrong.append(f"{name} {have} (lock: {version})")
    assert not wrong, "installed versions differ from the lock (run `make clean install`): " + ", ".join(wrong)
