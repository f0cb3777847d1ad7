"""The shipped model checkpoints/ycbv3.pt, trained only on argen captures of the three ycbv_real meshes: on two
real frames of the development set (Asus Xtion, YCB-Video) it finds the objects within 10 % ADD(-S)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

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


def test_shipped_model_finds_the_objects_in_two_real_frames(ycbv_real, tmp_path):
    run_label(LabelRequest(dataset=ycbv_real, split="test", out=tmp_path / "l.h5", progress=False,
                           cfg=LabelConfig(max_depth=1.5)))
    ck = load_checkpoint(CKPT)
    objects = checkpoint_objects(ck)[0]
    cfg = checkpoint_geometry_config(ck, None, True)
    s = evaluate(network_predictor(ck), tmp_path / "l.h5", tmp_path / "rep", icp=True, cfg=cfg, frames=[3, 4],
                 min_visib=0.0, poser=checkpoint_poser(ck, objects))
    errs = np.array([r["icp"] / r["diameter"] for r in s["instances"]])
    assert len(errs) == 6
    # the shipped model gets the gelatin box right in both frames and the foam brick in the second (the mug not:
    # RESULTS.md); a model that finds nothing, or finds the objects but not their orientation, gets none
    assert np.sum(errs < 0.1) >= 2, np.round(errs, 3)
