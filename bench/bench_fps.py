"""Benchmark stage 1's farthest point sampling on CPU: fpsample's exact loop from index 0 against its tree-based
exact FPS (``bucket_fps_kdline``, what :func:`detector.stage1.ops.fps_numpy` uses on clouds of
more than ``EXACT_FPS_MAX_POINTS`` points, and at inference on every cloud with ``sampling.fps: tree``), and the whole
of :func:`detector.stage1.ops.precompute_indices` per size as training computes it (the loop up to 4096 points).

    .venv/bin/python bench/bench_fps.py [--data data/lm_test.h5] [--frames 20] [--rounds 3]

Input: the first ``--frames`` frames of a label file (each frame's points drawn as stage 1 draws them, seed 0), or
without ``--data`` a synthetic desk scene. Sizes (input points / keypoints): the cpu preset's 4096 / 1024; denser
inference, ``sampling.density`` 1.25, 1.5 and 2 (5120 / 1280, 6144 / 1536, 8192 / 2048); the paper preset's
16384 / 4096. The two forms alternate frame by frame, ``--rounds`` times; medians over all frames and rounds, ms.
Also checks that both forms are exact FPS sequences (each next point a farthest one, float32 rounding aside). One
JSON line per size.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import fpsample
import numpy as np

from detector.stage1.dataset import frame_rows
from detector.stage1.ops import TREE_FPS_HEIGHT, precompute_indices
from detector.stage1.network import preset

SIZES = [(4096, 1024), (5120, 1280), (6144, 1536), (8192, 2048), (16384, 4096)]


def clouds(path: str | None, frames: int) -> list[np.ndarray]:
    """(N, 9) float32 feature arrays of real label-file frames, or synthetic desk scenes (a plane and boxes)."""
    if path:
        from argen.h5 import LabelFile

        with LabelFile(path) as lf:
            return [np.asarray(lf.frame(i).features, np.float32) for i in range(min(frames, lf.num_frames))]
    rng = np.random.default_rng(0)
    out = []
    for _ in range(frames):
        n = 30000
        plane = np.c_[rng.uniform(-0.6, 0.6, (n, 2)), np.full(n, 1.0)]
        boxes = rng.uniform(-0.03, 0.03, (n // 5, 3)) + rng.uniform(-0.4, 0.4, (n // 5, 1)) * [1, 1, 0]
        out.append(np.c_[np.r_[plane, boxes + [0, 0, 0.95]], np.zeros((n + n // 5, 6))].astype(np.float32))
    return out


def exact_gap(xyz: np.ndarray, order: np.ndarray) -> float:
    """Largest relative shortfall of a chosen point's distance from the farthest one's (0 for exact FPS)."""
    p = xyz.astype(np.float64)
    d = ((p - p[order[0]]) ** 2).sum(1)
    worst = 0.0
    for i in order[1:]:
        worst = max(worst, (d.max() - d[i]) / max(d.max(), 1e-12))
        d = np.minimum(d, ((p - p[i]) ** 2).sum(1))
    return worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None, help="a label file (argen label); default: synthetic scenes")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    frames = clouds(args.data, args.frames)
    base = preset("cpu")
    for n, k in SIZES:
        xyzs = [f[frame_rows(f, n, np.random.default_rng(0)), :3].copy() for f in frames]
        t = {"loop": [], "tree": [], "indices": []}
        gaps = {"loop": 0.0, "tree": 0.0}
        specs = [(k, *base.sampling_specs()[0][1:])] + list(base.sampling_specs()[1:])
        for r in range(args.rounds):
            for xyz in xyzs:
                for form in ("loop", "tree") if r % 2 == 0 else ("tree", "loop"):
                    t0 = time.perf_counter()
                    order = (fpsample.fps_sampling(xyz, k, start_idx=0) if form == "loop" else
                             fpsample.bucket_fps_kdline_sampling(xyz, k, h=TREE_FPS_HEIGHT, start_idx=0))
                    t[form].append(time.perf_counter() - t0)
                    if r == 0:
                        gaps[form] = max(gaps[form], exact_gap(xyz, order))
                t0 = time.perf_counter()
                precompute_indices(xyz, specs)
                t["indices"].append(time.perf_counter() - t0)
        ms = {f: round(1000 * statistics.median(v), 2) for f, v in t.items()}
        print(json.dumps({"points": n, "keypoints": k, "frames": len(xyzs), "fps_loop_ms": ms["loop"],
                          "fps_tree_ms": ms["tree"], "ratio": round(ms["loop"] / ms["tree"], 1),
                          "precompute_indices_ms": ms["indices"],
                          "max_relative_gap": {f: float(f"{g:.1e}") for f, g in gaps.items()}}), flush=True)


if __name__ == "__main__":
    main()
