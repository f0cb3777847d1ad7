"""Shared test fixtures: paths to the shared LineMOD data (tests skip when it is absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

REPO = Path(__file__).resolve().parents[1]
LM_DIR = REPO.parent / "shared" / "data" / "lm"
YCBV_REAL_DIR = REPO.parent / "shared" / "data" / "ycbv_real"


@pytest.fixture(scope="session")
def lm_models() -> Path:
    """The shared LineMOD models folder (BOP, mm); skips the test when it is not there."""
    d = LM_DIR / "models"
    if not (d / "models_info.json").is_file():
        pytest.skip("shared LineMOD data not available")
    return d


@pytest.fixture(scope="session")
def ycbv_real() -> Path:
    """The shared real YCB-Video development frames (BOP); skips the test when they are not there."""
    if not (YCBV_REAL_DIR / "test" / "000000" / "scene_gt.json").is_file():
        pytest.skip("shared ycbv_real data not available")
    return YCBV_REAL_DIR


def load_repo_script(rel: str):
    """A script of the repository (e.g. ``bench/probe_stage1.py``) imported as a module named after its file; the
    module is registered in ``sys.modules`` first (dataclasses look their module up while a class is built)."""
    import importlib.util
    import sys

    path = REPO / rel
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="session")
def repo_script():
    """:func:`load_repo_script` as a fixture: ``repo_script("bench/probe_misses.py")``."""
    return load_repo_script
