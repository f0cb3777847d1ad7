"""Seconds per training step (batch 4) of the detector presets, and peak memory.

Usage: .venv/bin/python bench/bench_train.py [--preset cpu paper] [--steps 5] [--device cpu|cuda] [--data FILE.h5]

Each preset runs in its own process (so peak RSS is per preset). A step is forward + backward + AdamW
on a prepared batch (median over ``--steps`` after one warm-up step); data time is the median time to make
one batch of items in one process (sampling, augmentation, neighbour indices: the work of the loader
workers). Without ``--data`` a synthetic label file of 160x120-pixel frames (up to 19,200 points) is used.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def one_preset(preset: str, steps: int, device_name: str, data: Path) -> dict:
    """Measure one preset in this process; returns a dict of numbers."""
    import torch

    from detector.data.batches import collate
    from detector.stage1.dataset import PointDataset
    from detector.stage1.train import build_model_config, forward_loss, make_config
    from detector.training.devices import resolve_device

    cfg = make_config(preset, {"batch_size": 4, "device": device_name})
    device = resolve_device(cfg.device)
    use_indices = device.type == "cpu"
    model_cfg = build_model_config(cfg)
    ds = PointDataset(data, model_cfg, cfg.num_points, augment=True, seed=0, precompute=use_indices)
    from detector.stage1.network import PointNet2

    torch.manual_seed(0)
    model = PointNet2(model_cfg, num_classes=len(ds.class_ids)).to(device)
    params = sum(p.numel() for p in model.parameters())
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    data_times, step_times = [], []
    batches = []
    for s in range(steps + 1):
        t = time.perf_counter()
        batches.append(collate([ds[(s, i % len(ds))] for i in range(4 * s, 4 * s + 4)]))
        data_times.append(time.perf_counter() - t)
    for batch in batches:
        if device.type == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        loss, _ = forward_loss(model, batch, cfg.loss, device, use_indices)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        step_times.append(time.perf_counter() - t)
    out = {"preset": preset, "device": str(device), "num_points": cfg.num_points, "params": params,
           "step_s": statistics.median(step_times[1:]), "data_s_per_batch": statistics.median(data_times[1:]),
           "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "torch_threads": torch.get_num_threads()}
    if device.type == "cuda":
        out["peak_cuda_mib"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", nargs="+", default=["cpu", "paper"])
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(one_preset(args.preset[0], args.steps, args.device, args.data)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            sys.path.insert(0, str(REPO / "tests"))
            from test_data import write_synthetic_h5

            data = write_synthetic_h5(Path(tmp) / "bench.h5", num_frames=8, seed=0, width=160, height=120)
        print("command:", " ".join([Path(sys.executable).name, *sys.argv]))
        for p in args.preset:
            res = subprocess.run([sys.executable, __file__, "--child", "--preset", p, "--steps", str(args.steps),
                                  "--device", args.device, "--data", str(data)], capture_output=True, text=True)
            if res.returncode != 0:
                print(f"{p}: failed\n{res.stderr}")
                continue
            r = json.loads(res.stdout.strip().splitlines()[-1])
            line = (f"{r['preset']:>6} on {r['device']}: {r['step_s']:.3f} s/step at batch 4 "
                    f"({r['num_points']} points, {r['params'] / 1e6:.2f} M parameters, {r['torch_threads']} threads), "
                    f"data {r['data_s_per_batch']:.3f} s/batch in one process, peak RSS {r['peak_rss_mib']:.0f} MiB")
            if "peak_cuda_mib" in r:
                line += f", peak CUDA {r['peak_cuda_mib']:.0f} MiB"
            print(line, flush=True)


if __name__ == "__main__":
    main()
