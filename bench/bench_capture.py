"""Benchmark `argen capture-sim` on the linemod template: frames/s and a per-stage breakdown.

    .venv/bin/python bench/bench_capture.py [--frames 40] [--workers 1 2] [--models DIR]

Runs each worker count on a fresh output folder (640x480, 3-4 objects, clutter, Kinect noise) and
prints a markdown table: frames/s over the whole run (start-up included) and, for 1 worker, the
median seconds per frame of each stage (scene, render, AR step, noise, write).
"""

from __future__ import annotations

import argparse
import platform
import shutil
import tempfile
import time
from pathlib import Path

from argen.config import load_template
from argen.models.objects import load_objects
from argen.sim.capture import CaptureRequest, run_capture


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--models", type=Path, default=None)
    args = ap.parse_args()
    cfg = load_template("linemod")
    objs = load_objects(args.models, None)
    print(f"machine: {platform.processor() or platform.machine()}, {__import__('os').cpu_count()} cores; "
          f"objects: {'builtin' if args.models is None else args.models}; frames: {args.frames}")
    print("| workers | frames/s | accepted | rejected | scene | render | AR | noise | write |")
    print("|---|---|---|---|---|---|---|---|---|")
    base = None
    for w in args.workers:
        out = Path(tempfile.mkdtemp(prefix="bench_capture_"))
        try:
            t0 = time.perf_counter()
            s = run_capture(CaptureRequest(cfg=cfg, objects=objs, out=out, frames=args.frames, workers=w,
                                           models_source=str(args.models or "builtin"), progress=False))
            dt = time.perf_counter() - t0
        finally:
            shutil.rmtree(out, ignore_errors=True)
        fps = args.frames / dt
        base = base or fps
        n = max(s.written + s.rejected, 1)
        per = {k: s.stage_seconds.get(k, 0.0) / n for k in ("scene", "render", "ar", "noise", "write")}
        cols = " | ".join(f"{per[k] * 1000:.0f} ms" for k in per) if w == 1 else " | ".join("-" for _ in per)
        print(f"| {w} | {fps:.2f} ({fps / base:.2f}x) | {s.written} | {s.rejected} | {cols} |", flush=True)


if __name__ == "__main__":
    main()
