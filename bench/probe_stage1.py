"""Stage-1 check: how far a two-stage model's stage-1 centres are from the true box centres (the crop jitter
stage 2 must forgive), how many instances get a centre at all, and per object how many of its sampled points
stage 1 labels right (and how many background points it takes for an object), and which object it takes each
object's instances for (the most common object label among an instance's sampled points). Usage:
python bench/probe_stage1.py CKPT LABELS [--frames N] [--min-visib V] (CKPT: a stage-1 run's last.pt or a
two-stage model.pt)."""

from __future__ import annotations

import argparse

import numpy as np
import torch
from scipy.spatial import cKDTree

from argen.h5 import LabelFile
from detector.checkpoint import load_checkpoint
from detector.geometry.types import GeometryConfig, ObjectInfo
from detector.geometry.voting import detect
from detector.stage1.predictor import network_predictor


def taken_object(labels: np.ndarray, own: int) -> int:
    """The object an instance is taken for: the most common object label among its sampled points' labels
    (labels: (n,) int, 0 = background), its own object ``own`` where that ties for the most, 0 where no point
    is labelled an object."""
    counts = np.bincount(labels[labels > 0], minlength=own + 1)
    if not counts.any():
        return 0
    return own if counts[own] == counts.max() else int(counts.argmax())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("ckpt")
    ap.add_argument("labels")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--tau", type=float, default=0.3)
    ap.add_argument("--min-visib", type=float, default=0.1)
    a = ap.parse_args()
    torch.set_num_threads(1)
    # a stage-1 run's last.pt or a two-stage model.pt: its stage 1 is the model, sampling a frame once and as it
    # trained (the counts below are of one draw's points, its keypoints by the training's FPS, the centres of 3 votes)
    ck = load_checkpoint(a.ckpt, sampling={"passes": 1, "fps": "trained"})
    pred = network_predictor(ck)
    objs = ObjectInfo.from_table(ck.objects)
    errs, found, total = [], 0, 0
    points = {}  # obj_id: [instances, sampled points, labelled right, centre found]
    false_fg = sampled = 0
    taken_for = {}  # obj_id: {object label most of its instance's points get (0: none): instances}
    with LabelFile(a.labels) as lf:
        for i in range(min(a.frames, lf.num_frames)):
            f = lf.frame(i)
            p = pred(f)
            dets = detect(p.xyz, p.obj_ids, p.confidence, p.control_points, objs,
                          GeometryConfig(tau=a.tau, centre_votes=True))
            rows = cKDTree(np.asarray(f.features[:, :3], np.float64)).query(p.xyz)[1]  # the sampled points' rows
            sem, ins, pred_ids = np.asarray(f.semantic)[rows], np.asarray(f.instance)[rows], p.obj_ids
            false_fg += int(np.sum((sem == 0) & (pred_ids > 0)))
            sampled += len(rows)
            inst = f.instances
            for g in range(len(inst)):
                if inst.visib_fract[g] < a.min_visib:
                    continue
                total += 1
                oid = int(inst.obj_id[g])
                c = inst.control_points[g][8]
                d = [np.linalg.norm(x.control_points[8] - c) for x in dets if x.obj_id == oid]
                hit = bool(d and min(d) < 0.1)
                if hit:
                    found += 1
                    errs.append(min(d))
                mine = ins == g
                row = points.setdefault(oid, [0, 0, 0, 0])
                row[0] += 1
                row[1] += int(mine.sum())
                row[2] += int(np.sum(mine & (pred_ids == oid)))
                row[3] += int(hit)
                if mine.any():  # an instance none of whose points were sampled is in neither table's counts
                    taken = taken_for.setdefault(oid, {})
                    top = taken_object(pred_ids[mine], oid)
                    taken[top] = taken.get(top, 0) + 1
    e = np.array(errs) * 100
    print(f"{total} instances, {found} with a centre within 10 cm ({100 * found / max(total, 1):.1f} %); "
          f"centre error cm: median {np.median(e):.2f}, p90 {np.percentile(e, 90):.2f}, "
          f"per-axis RMS {np.sqrt(np.mean(e ** 2) / 3):.2f}")
    print(f"background points taken for an object: {false_fg} of {sampled} sampled")
    print("| object | instances | sampled points | labelled right | instances with a centre within 10 cm |")
    print("|---|---:|---:|---:|---:|")
    for oid, (n, pts, right, hit) in sorted(points.items()):
        print(f"| {oid} | {n} | {pts} | {right} ({100 * right / max(pts, 1):.0f} %) | {hit} |")
    print("\nwhich object each object's instances are taken for (the most common object label among an instance's")
    print("sampled points, its own where that ties; 0: none of them labelled an object; instances without sampled")
    print("points left out)")
    print("| object | instances: taken for (count) |")
    print("|---|---|")
    for oid, row in sorted(taken_for.items()):
        print(f"| {oid} | " + ", ".join(f"{k} ({v})" for k, v in sorted(row.items(), key=lambda kv: -kv[1])) + " |")


if __name__ == "__main__":
    main()
