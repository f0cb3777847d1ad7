"""The shipped model checkpoints/ycbv3.pt, trained only on argen captures of the three ycbv_real meshes: on the real
frames of the development set (Asus Xtion, YCB-Video) it finds objects within 10 % ADD(-S), and its stage 1 labels
the real mug."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from argen.h5 import LabelFile
from argen.label import LabelConfig, LabelRequest, run_label
from detector.checkpoint import load_checkpoint
from detector.evaluate import evaluate
from detector.infer import checkpoint_geometry_config, checkpoint_objects, checkpoint_poser
from detector.stage1.predictor import network_predictor

CKPT = Path(__file__).resolve().parents[1] / "checkpoints" / "ycbv3.pt"


def test_shipped_model_is_small_and_complete():
    assert CKPT.is_file(), "checkpoints/ycbv3.pt is part of the repository"
    assert CKPT.stat().st_size <= 10 * 2**20
    ck = load_checkpoint(CKPT)
    assert ck.stage2_net is not None and sorted(ck.class_ids) == [8, 14, 21]


@pytest.fixture(scope="module")
def real_labels(ycbv_real, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ycbv3") / "l.h5"
    run_label(LabelRequest(dataset=ycbv_real, split="test", out=out, progress=False, cfg=LabelConfig(max_depth=1.5)))
    return out


def test_shipped_model_finds_the_objects_in_the_real_frames(real_labels, tmp_path):
    ck = load_checkpoint(CKPT)
    objects = checkpoint_objects(ck)[0]
    cfg = checkpoint_geometry_config(ck, None, True)
    s = evaluate(network_predictor(ck), real_labels, tmp_path / "rep", icp=True, cfg=cfg, min_visib=0.0,
                 poser=checkpoint_poser(ck, objects))
    errs = np.array([np.inf if r["icp"] is None else r["icp"] / r["diameter"] for r in s["instances"]])
    assert len(errs) == 30
    # the shipped model (run K, seed 0) gets the foam brick right in 10 of 10 frames and the gelatin box in 7 (the
    # box's way round chosen by its print, geometry.colour_check; the mug's handle is hidden: RESULTS.md); a model
    # that finds nothing, or finds the objects but not their orientation, gets none
    assert np.sum(errs < 0.1) >= 13, np.round(errs, 3)
    box = np.array([r["obj_id"] == 8 for r in s["instances"]])
    assert np.sum(errs[box] < 0.1) >= 6, np.round(errs[box], 3)


def test_the_print_turns_the_real_gelatin_box(real_labels, tmp_path):
    """Without the colour check the same model turns the gelatin box the wrong way in 9 of 10 frames (RESULTS.md):
    what the test above counts comes from the print, not from the depth."""
    ck = load_checkpoint(CKPT)
    objects = checkpoint_objects(ck)[0]
    cfg = replace(checkpoint_geometry_config(ck, None, True), colour_check=False)
    s = evaluate(network_predictor(ck), real_labels, tmp_path / "rep", icp=True, cfg=cfg, min_visib=0.0,
                 poser=checkpoint_poser(ck, objects))
    errs = np.array([np.inf if r["icp"] is None else r["icp"] / r["diameter"] for r in s["instances"] if r["obj_id"] == 8])
    assert np.sum(errs < 0.1) <= 2, np.round(errs, 3)


def test_shipped_stage1_labels_the_real_mug(real_labels):
    """Stage 1, trained without distractors (examples/ycbv_real/run.sh), labels most of the real mug's sampled
    points mug; trained among cup-sized distractors it labelled 4 % of them so (RESULTS.md, runs D and F)."""
    ck = load_checkpoint(CKPT)
    pred = network_predictor(ck)
    mug = right = 0
    with LabelFile(real_labels) as lf:
        for i in (0, 5):
            f = lf.frame(i)
            p = pred(f)
            rows = cKDTree(np.asarray(f.features[:, :3], np.float64)).query(p.xyz)[1]
            on_mug = np.asarray(f.semantic)[rows] == 14
            mug += int(on_mug.sum())
            right += int(np.sum(on_mug & (np.asarray(p.obj_ids) == 14)))
    assert mug > 50
    assert right / mug > 0.5, (right, mug)
