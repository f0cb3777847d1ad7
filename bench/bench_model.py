"""Benchmark PointNet2 training steps: forward + backward seconds per step and peak memory, per preset.

    .venv/bin/python bench/bench_model.py [--presets cpu paper] [--batch 4] [--steps 5] [--threads 2]
                                          [--device cpu|cuda] [--torch-indices]

Input: a synthetic scene (table plane plus a few boxes, camera metres) of the preset's natural size
(cpu: 4096 points, paper: 16384). Indices are precomputed with detector.stage1.ops.precompute_indices (as the
data loader workers do; their time per cloud is reported separately) unless ``--torch-indices``, which
lets the model compute them in torch inside the step (the GPU path). The step is forward + multitask loss
+ backward + AdamW step; the median of ``--steps`` steps after one warm-up step is reported. Peak memory
is the process's max RSS (resource.getrusage; CPU) or torch.cuda.max_memory_allocated (CUDA). One JSON
line per preset on stdout.
"""

from __future__ import annotations

import argparse
import json
import resource
import shlex
import statistics
import sys
import time

import numpy as np
import torch

from detector.stage1.loss import LossConfig, multitask_loss
from detector.stage1.network import PointNet2, preset
from detector.stage1.ops import precompute_indices
from detector.stage1.train import keypoint_targets

NUM_POINTS = {"cpu": 4096, "paper": 16384}


def synthetic_scene(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """features (n, 9) float32, cls (n,) int64 in {0, 1}, control_points (n, 9, 3): a plane with 3 boxes."""
    m = n // 3
    plane = np.c_[rng.uniform(-0.4, 0.4, (n - m, 2)), np.zeros(n - m)]
    centres = rng.uniform(-0.25, 0.25, (3, 3)) * [1, 1, 0] + [0, 0, -0.06]
    which = rng.integers(0, 3, m)
    boxes = centres[which] + rng.uniform(-0.06, 0.06, (m, 3))
    xyz = np.r_[plane, boxes] + [0, 0, 0.9]
    feats = np.c_[xyz, rng.uniform(0, 1, (n, 3)), np.tile([0, 0, -1.0], (n, 1))].astype(np.float32)
    cls = np.r_[np.zeros(n - m), np.ones(m)].astype(np.int64)
    corners = np.array([[x, y, z] for x in (-.06, .06) for y in (-.06, .06) for z in (-.06, .06)] + [[0, 0, 0]])
    cps = np.zeros((n, 9, 3), np.float32)
    cps[n - m:] = centres[which][:, None] + corners + [0, 0, 0.9]
    return feats, cls, cps


def bench(name: str, batch: int, steps: int, device: torch.device, torch_indices: bool) -> dict:
    """Median seconds per training step of one preset, and loader-side index time per cloud."""
    cfg = preset(name)
    n = NUM_POINTS[name]
    rng = np.random.default_rng(0)
    scenes = [synthetic_scene(n, rng) for _ in range(batch)]
    t0 = time.perf_counter()
    per = [precompute_indices(s[0][:, :3], cfg.sampling_specs()) for s in scenes]
    index_s = (time.perf_counter() - t0) / batch
    idx = None if torch_indices else {k: torch.from_numpy(np.stack([p[k] for p in per])).to(device) for k in per[0]}
    x = torch.from_numpy(np.stack([s[0] for s in scenes])).to(device)
    cls = torch.from_numpy(np.stack([s[1] for s in scenes])).to(device)
    cps = torch.from_numpy(np.stack([s[2] for s in scenes])).to(device)
    torch.manual_seed(0)
    model = PointNet2(cfg, num_classes=1).to(device).train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    times = []
    for _ in range(steps + 1):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        out = model(x, idx)
        target = keypoint_targets({"cls": cls, "control_points": cps}, out["keypoints"])
        loss, _ = multitask_loss(out, target, LossConfig())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    peak = (torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda"
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    return {"preset": name, "points": n, "keypoints": cfg.npoints[0], "batch": batch, "device": str(device),
            "threads": torch.get_num_threads(), "indices": "torch" if torch_indices else "precomputed",
            "params": sum(p.numel() for p in model.parameters()),
            "step_s_median": round(statistics.median(times[1:]), 4), "step_s_all": [round(v, 4) for v in times[1:]],
            "index_s_per_cloud": round(index_s, 4), "peak_mem_mib": round(peak, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=["cpu", "paper"], choices=sorted(NUM_POINTS))
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--torch-indices", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print("$", shlex.join([sys.executable, *sys.argv]), flush=True)
    for name in args.presets:
        print(json.dumps(bench(name, args.batch, args.steps, torch.device(args.device), args.torch_indices)),
              flush=True)


if __name__ == "__main__":
    main()
