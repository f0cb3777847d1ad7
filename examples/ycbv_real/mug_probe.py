"""How stage 2 poses an object about its part symmetry's axis (RESULTS.md, "The mug's hidden handle"): for each frame,
the stage-1 detections of the object near its true centre are cropped as at inference, and the script prints how many
of the crop's points are the object's and how many of those stage 2 calls foreground, how far its model coordinates
lie from the axis against the true ones (medians), how many of the odd part's samples (the handle) the frame's depth
sees at the true pose (``detector.geometry.verify.depth_votes``, the part check's count), how far the centre of its pose (its box's: with the handle turned
away, a turn moves it) lies from the true centre, and how far its pose puts the axis from the true one.

    python examples/ycbv_real/mug_probe.py MODEL LABELS OBJ_ID [--seed S]

The axis is the one ``argen label`` found for OBJ_ID and stored in LABELS' object table
(``argen.models.symmetry.find_part_symmetry``); it is only measured against, nothing is changed.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from argen.errors import ArgenError
from argen.h5 import LabelFile
from argen.models.symmetry import rotation_angle_axis
from detector.checkpoint import load_checkpoint
from detector.errors import DetectorError
from detector.geometry.icp import support_radius
from detector.geometry.verify import depth_votes, range_image
from detector.geometry.voting import detect
from detector.infer import checkpoint_geometry_config, checkpoint_objects, checkpoint_poser
from detector.stage1.predictor import network_predictor
from detector.stage1.sampling import FPS_CHOICES
from detector.stage2.crops import model_coordinates
from detector.stage2.poser import crop_predictions


def axis_distance(points: np.ndarray, axis: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Distances (n,) metres of model-frame points (n,3) metres from the line through ``offset`` (3,) metres along
    ``axis`` (3,)."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    d = np.asarray(points, np.float64) - offset
    return np.linalg.norm(d - np.outer(d @ a, a), axis=1)


def turn_axis(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The axis (3,) unit and a point on it (3,), the transform's units, of a turn T (4,4) about a line: the
    rotation's fixed direction, and the point that (I - R) c = t gives nearest the origin."""
    _, axis = rotation_angle_axis(T[:3, :3])
    c = np.linalg.lstsq(np.eye(3) - T[:3, :3], T[:3, 3], rcond=None)[0]
    return axis, c - (c @ axis) * axis


def axis_error(R: np.ndarray, t: np.ndarray, R_true: np.ndarray, t_true: np.ndarray, axis: np.ndarray,
               offset: np.ndarray) -> tuple[float, float]:
    """How far a pose (R (3,3), t (3,) metres) puts the model's axis (``axis`` (3,) through ``offset`` (3,) metres,
    model frame) from where the true pose puts it: the distance across the true axis between the two axes' points
    at the model's origin height (mm), and the angle between them (degrees). A turn about the axis changes
    neither."""
    a_true, a = R_true @ axis, R @ axis
    d = (R @ offset + t) - (R_true @ offset + t_true)
    across = np.linalg.norm(d - (d @ a_true) * a_true)
    return 1000 * float(across), float(np.degrees(np.arccos(min(1.0, abs(float(a_true @ a))))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("labels")
    ap.add_argument("obj_id", type=int)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fps", choices=FPS_CHOICES, default=None,
                    help="stage 1's farthest point sampling (sampling.fps; default: the model file's)")
    a = ap.parse_args()
    try:
        with LabelFile(a.labels) as lf:
            tab = lf.objects
            turns = tab.part_symmetries[tab.index(a.obj_id)] if tab.part_symmetries else []
        if not len(turns):
            raise ValueError(f"{a.labels} stores no part symmetry (an axis) for object {a.obj_id}")
        axis, offset = turn_axis(np.asarray(turns[0], np.float64))
        ck = load_checkpoint(a.model, sampling={"fps": a.fps} if a.fps else None)
    except (OSError, ValueError, KeyError, IndexError, ArgenError, DetectorError) as exc:
        sys.exit(f"mug_probe: {exc}")
    objects, _ = checkpoint_objects(ck)
    cfg = checkpoint_geometry_config(ck, None, True, None, [])
    poser, pred = checkpoint_poser(ck, objects, "cpu", a.seed), network_predictor(ck, a.seed)
    odd = objects.odd_points.get(a.obj_id, np.zeros((0, 3)))
    tol = cfg.depth_tolerance * support_radius(cfg.support_distance, cfg.support_floor, objects.diameters[a.obj_id])
    print("| frame | odd part seen at the true pose | object points in crop | called foreground | axis distance true / "
          "predicted (cm) | pose centre off (cm) | pose axis off (mm) / tilted (deg) | score |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    with LabelFile(a.labels) as lf:
        for i in range(lf.num_frames):
            fr = lf.frame(i)
            inst = fr.instances
            p = pred(fr)
            dets = detect(p.xyz, p.obj_ids, p.confidence, p.control_points, objects, cfg, {})
            ri = range_image(np.asarray(fr.features[:, :3], np.float64))
            for g in np.flatnonzero(inst.obj_id == a.obj_id):
                c, dia = inst.control_points[g][8], objects.diameters[a.obj_id]
                seen = depth_votes(ri, odd, inst.R[g][None].astype(np.float64), inst.t[g][None].astype(np.float64),
                                   tol, 2 * tol)[0][0] if len(odd) else 0
                shown = f"{int(seen)} of {len(odd)}"
                for d in dets:
                    if d.obj_id != a.obj_id or np.linalg.norm(d.control_points[8] - c) >= 0.5 * dia:
                        continue
                    out = crop_predictions(poser.net, fr.features, d.control_points[8][None],
                                           np.array([poser.class_ids.index(a.obj_id)]), np.array([dia]),
                                           poser.crop_cfg, poser.normalisation, a.seed)[0]
                    if out is None:
                        print(f"| {i} | {shown} | crop too small | | | | | |")
                        continue
                    rows, prob, mxyz = out
                    own = np.asarray(fr.instance)[rows] == g
                    true = model_coordinates(fr.features[rows, :3], inst.R[g], inst.t[g], 1.0)[own]
                    r_true, r_pred = axis_distance(true, axis, offset), axis_distance(mxyz[own], axis, offset)
                    posed = poser([d], fr.features)
                    off = f"{100 * np.linalg.norm(posed[0].control_points[8] - c):.1f}" if posed else "no pose"
                    axis_off = ("{:.1f} / {:.1f}".format(*axis_error(posed[0].R, posed[0].t, inst.R[g], inst.t[g],
                                                                    axis, offset)) if posed else "")
                    score = f"{posed[0].score:.2f}" if posed else ""
                    print(f"| {i} | {shown} | {int(own.sum())} of {len(rows)} | {int(((prob >= 0.5) & own).sum())} | "
                          f"{100 * np.median(r_true):.1f} / {100 * np.median(r_pred):.1f} | {off} | {axis_off} | "
                          f"{score} |")


if __name__ == "__main__":
    main()
