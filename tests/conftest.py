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
