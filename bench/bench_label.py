"""Benchmark `argen label` on linemod-template frames (640x480, Kinect noise): frames/s on one process.

    .venv/bin/python bench/bench_label.py [--frames 20] [--repeats 3] [--models DIR] [--dataset DIR] [--workers 1,2]

Makes a capture-sim dataset once (LineMOD models from ../shared/data/lm when there, else the built-in
objects; skipped with --dataset), then labels it ``--repeats`` times with one process and prints the
median frames/s of the whole run (model loading, labelling, part files and the final file included)
and of ``label_frame`` alone. ``--workers 1,2`` times whole runs with each worker count, interleaved
(1, 2, 1, 2, ...) so that both see the same machine load, and prints the speed-up of the medians.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from argen.label import LabelConfig, Labeller, LabelRequest, dataset_frames, load_label_objects, run_label

LM = Path(__file__).resolve().parents[2] / "shared/data/lm/models"


def make_dataset(out: Path, frames: int, models: Path | None) -> None:
    from argen.config import load_template
    from argen.models.objects import load_objects
    from argen.sim.capture import CaptureRequest, run_capture

    cfg = load_template("linemod")
    sel = ["ape", "can", "cat", "driller", "duck"] if models else None
    objs = load_objects(models, sel)
    run_capture(CaptureRequest(cfg=cfg, objects=objs, out=out, frames=frames, workers=1,
                               models_source=str(models or "builtin"), progress=False))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--models", type=Path, default=LM if (LM / "models_info.json").is_file() else None)
    ap.add_argument("--dataset", type=Path, default=None, help="label this BOP dataset instead of making one")
    ap.add_argument("--max-points", type=int, default=30000)
    ap.add_argument("--workers", default="1", help="comma-separated worker counts to compare, e.g. 1,2")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_label_"))
    try:
        ds = args.dataset
        if ds is None:
            ds = tmp / "ds"
            make_dataset(ds, args.frames, args.models)
        scenes, frames = dataset_frames(ds, "train_pbr")
        print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; dataset: {ds} "
              f"({len(frames)} frames, models: {args.models or 'builtin'}); max_points {args.max_points}")
        cfg = LabelConfig(max_points=args.max_points)
        counts = [int(w) for w in args.workers.split(",")]
        rates: dict[int, list[float]] = {w: [] for w in counts}
        out = tmp / "out.h5"
        for _ in range(args.repeats):
            for w in counts:
                out.unlink(missing_ok=True)
                t0 = time.perf_counter()
                run_label(LabelRequest(dataset=ds, split="train_pbr", out=out, cfg=cfg, progress=False, workers=w))
                rates[w].append(len(frames) / (time.perf_counter() - t0))
        runs = rates[counts[0]]
        ids = sorted({g.obj_id for s in scenes.values() for gl in s.gts.values() for g in gl})
        lab = Labeller(load_label_objects(ds / "models", ids), LabelConfig(max_points=args.max_points, max_depth=1.75))
        per = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            for sid, im in frames:
                lab.label_frame(scenes[sid], im)
            per.append(len(frames) / (time.perf_counter() - t0))
        size = out.stat().st_size / len(frames) / 1e6
        print(f"command: argen label {ds} --split train_pbr --out X.h5 --max-points {args.max_points}")
        for w in counts:
            print(f"whole run ({w} worker{'s' if w > 1 else ''}): median {statistics.median(rates[w]):.1f} frames/s "
                  f"(runs: {', '.join(f'{v:.1f}' for v in rates[w])}); file {size:.2f} MB per frame")
        for w in counts[1:]:
            print(f"speed-up {w} vs {counts[0]} workers: "
                  f"{statistics.median(rates[w]) / statistics.median(rates[counts[0]]):.2f}x")
        print(f"label_frame only: median {statistics.median(per):.1f} frames/s")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
