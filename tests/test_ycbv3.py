"""The shipped model checkpoints/ycbv3.pt, trained only on argen captures of the three ycbv_real meshes: on the real
frames of the development set (Asus Xtion, YCB-Video) it finds objects within 10 % ADD(-S), and its stage 1 labels
the real mug."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from argen.h5 import LabelFile
from argen.label import LabelConfig, LabelRequest, run_label
from detector.checkpoint import load_checkpoint
from detector.evaluate import evaluate
from detector.geometry.types import ObjectInfo
from detector.infer import checkpoint_geometry_config, checkpoint_objects, checkpoint_poser
from detector.stage1.predictor import network_predictor

CKPT = Path(__file__).resolve().parents[1] / "checkpoints" / "ycbv3.pt"


def test_shipped_model_is_small_and_complete():
    assert CKPT.is_file(), "checkpoints/ycbv3.pt is part of the repository"
    assert CKPT.stat().st_size <= 10 * 2**20
    ck = load_checkpoint(CKPT)
    assert ck.stage2_net is not None and sorted(ck.class_ids) == [8, 14, 21]
    # the surface-continuation check (on by default) needs each object's surface samples with unit normals
    surfaces = ObjectInfo.from_table(ck.objects).surfaces
    assert sorted(surfaces) == sorted(ck.class_ids)
    for pts, normals in surfaces.values():
        assert pts.shape == normals.shape and len(pts) >= 1000
        assert np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-4)


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
    box = np.array([r["obj_id"] == 8 for r in s["instances"]])
    assert len(box) == 30
    # the shipped model (run M, seed 0) gets the foam brick right in 9 and 10 of 10 frames without and with ICP and
    # the gelatin box in 10 and 10 (the box's way round chosen by its print, geometry.colour_check; the mug's handle
    # is hidden: RESULTS.md); a model that finds nothing, or finds the objects but not their orientation, gets none,
    # and run K's model (stage 2 with colour) got no gelatin box within 10 % before ICP
    for key in ("noicp", "icp"):
        errs = np.array([np.inf if r[key] is None else r[key] / r["diameter"] for r in s["instances"]])
        assert np.sum(errs < 0.1) >= 16, (key, np.round(errs, 3))
        assert np.sum(errs[box] < 0.1) >= 7, (key, np.round(errs[box], 3))


def test_the_print_turns_the_real_gelatin_box(real_labels):
    """Its shape allows the gelatin box three half turns that its print breaks; the model's stage 2, which sees no
    colour, is taught its pose only up to them, and the colour check chooses among them by the real frame's colours
    (RESULTS.md). Posed at its true pose turned each way, on its own labelled points, the check brings it back in
    nearly every real frame; with the frame's colours shuffled among its points it cannot (each frame's four starts
    end in one turn, the right one by chance)."""
    from detector.geometry.colour_check import colour_checked
    from detector.geometry.icp import turned_poses
    from detector.geometry.types import Detection

    ck = load_checkpoint(CKPT)
    objects = checkpoint_objects(ck)[0]
    cfg = checkpoint_geometry_config(ck, None, False)
    assert 8 in objects.texture and len(objects.shape_symmetries[8]) == 3
    right = shuffled_right = 0
    with LabelFile(real_labels) as lf:
        frames = [lf.frame(i) for i in range(lf.num_frames)]
    for i, f in enumerate(frames):
        g = int(np.flatnonzero(np.asarray(f.instances.obj_id) == 8)[0])
        rows = np.flatnonzero(np.asarray(f.instance) == g)
        R, t = np.asarray(f.instances.R[g], np.float64), np.asarray(f.instances.t[g], np.float64)
        Rk, tk = turned_poses(R, t, objects.shape_symmetries[8])
        dets = [Detection(8, 0.9, Rk[k], tk[k], 10, np.zeros((9, 3)), np.arange(3), points=rows) for k in range(4)]
        feats = np.asarray(f.features, np.float64)
        shuffled = feats[np.random.default_rng(i).permutation(len(feats)), 3:6]  # the frame's colours, print lost
        for colours, count in ((feats[:, 3:6], True), (shuffled, False)):
            out = colour_checked(dets, feats[:, :3], colours, objects, cfg, icp=False)
            back = sum(np.degrees(np.arccos(np.clip((np.trace(d.R.T @ R) - 1) / 2, -1, 1))) < 5.0
                       and np.linalg.norm(d.t - t) < 0.005 for d in out)  # back at the true pose (not a turn)
            if count:
                right += back
            else:
                shuffled_right += back
    # 4 starts (the true pose and its three turns) in each of 10 frames; measured 40 of 40 with the frames' colours,
    # 0 of 40 with them shuffled
    assert right >= 36, right
    assert shuffled_right <= 24, shuffled_right


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


def test_shipped_model_puts_the_real_mug_on_its_axis(real_labels):
    """The mug's handle is hidden in every frame, so its turn about its body is not in them; its axis is. The
    shipped model carries the part symmetry its stage 2 was taught under (the mug's model z axis), and after ICP
    its mug poses put that axis within 5 mm and 6 degrees of the true one in most frames (RESULTS.md, "The mug's
    hidden handle"; the previous model's stage 2, taught the mug exactly, put it 4-12 cm off)."""
    from argen.models.symmetry import rotation_angle_axis
    from detector.infer import estimate

    ck = load_checkpoint(CKPT)
    objects = checkpoint_objects(ck)[0]
    turns = objects.part_symmetries[14]
    assert len(turns) == 35 and len(objects.odd_points[14]) > 1000
    _, axis = rotation_angle_axis(turns[0][:3, :3])
    assert abs(axis[2]) > 0.99  # the YCB mug stands on its model z axis
    point = np.linalg.lstsq(np.eye(3) - turns[0][:3, :3], turns[0][:3, 3], rcond=None)[0]
    cfg = checkpoint_geometry_config(ck, None, True)
    pred, poser = network_predictor(ck), checkpoint_poser(ck, objects)
    on_axis = 0
    with LabelFile(real_labels) as lf:
        for i in range(lf.num_frames):
            fr = lf.frame(i)
            g = int(np.flatnonzero(fr.instances.obj_id == 14)[0])
            R, t = fr.instances.R[g].astype(float), fr.instances.t[g].astype(float)
            _, refined = estimate(pred(fr), objects, cfg, {}, fr.features[:, :3], poser, fr.features)
            mugs = [d for d in refined if d.obj_id == 14]
            if not mugs:
                continue
            d = max(mugs, key=lambda d: d.score)
            a_true = R @ axis
            off = (d.R @ point + d.t) - (R @ point + t)
            across = np.linalg.norm(off - (off @ a_true) * a_true)
            tilt = np.degrees(np.arccos(min(1.0, abs(float(a_true @ (d.R @ axis))))))
            on_axis += int(across < 0.005 and tilt < 6)
    assert on_axis >= 6, on_axis
