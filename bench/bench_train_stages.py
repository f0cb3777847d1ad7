"""The two-stage training's steps on this CPU: each stage alone on one and on two torch threads, and the two side by
side (stage 1 on one thread, stage 2 on one, each in its own process, as ``detector train`` runs them; README).

Usage: .venv/bin/python bench/bench_train_stages.py --data data/lm_train.h5 [--stage1-steps 300] [--stage2-steps 700]
       [--side-threads 1,2]

``--side-threads`` lists stage 1's thread counts for the side-by-side case (stage 2 always on one): 1 is how
``detector train`` runs them; 2 asks whether stage 1 on two threads, which gives the numbers of stage 1 trained alone
on two (one after the other, as ``checkpoints/lm8.pt``'s), shares the two cores as well.

Each case trains the default two-stage settings (``detector/presets/two-stage.yaml``) from scratch into a scratch
folder for a fixed number of steps, with its data-loader processes, in fresh processes. A stage's seconds a step are
the median over its steps after the first 250 (stage 2's first pass over the frames fills its crop cache and runs
slower; ``--skip``), read from the run's ``metrics.csv``; side by side, stage 2's are its steps after the skip that
end before stage 1 ends. "Work a second" side by side is the stage-1 steps a second times stage 1's seconds a step
alone on two threads, plus the same for stage 2: how many seconds of the stages trained one after the other (each on
two threads) a second side by side does; above 1 side by side is faster.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

#: Trains stage argv[1] ("stage1" / "stage2") on argv[2] threads for argv[3] steps from label file argv[4] into argv[5].
CHILD = """
import sys, torch
from detector.two_stage import load_two_stage_config
from detector.stage1.train import train
from detector.stage2.train import train_stage2
stage, threads, steps, data, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], sys.argv[5]
torch.set_num_threads(threads)
s1, s2, _, _ = load_two_stage_config(None).resolved()
if stage == "stage1":
    train(s1, data, out, progress=False, stop_after=steps)
else:
    train_stage2(s2, data, out, progress=False, stop_after=steps)
"""


def step_times(run: Path) -> tuple[list[int], list[float]]:
    """(steps, seconds of each) from a run's metrics.csv."""
    with open(run / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return [int(r["step"]) for r in rows], [1.0 / float(r["steps_per_s"]) for r in rows]


def start(stage: str, threads: int, steps: int, data: Path, out: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", CHILD, stage, str(threads), str(steps), str(data), str(out)])


def median_after(run: Path, skip: int, until: float | None = None) -> float:
    """Median seconds a step of ``run`` after step ``skip`` (and ending before ``until`` seconds into the run)."""
    steps, dt = step_times(run)
    t, keep = 0.0, []
    for s, d in zip(steps, dt):
        t += d
        if s > skip and (until is None or t <= until):
            keep.append(d)
    if not keep:
        raise SystemExit(f"{run}: no step after {skip} to time; give more steps")
    return statistics.median(keep)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="label file (argen label), e.g. data/lm_train.h5")
    ap.add_argument("--stage1-steps", type=int, default=300)
    ap.add_argument("--stage2-steps", type=int, default=700)
    ap.add_argument("--skip", type=int, default=250, help="steps not timed at the start of each run")
    ap.add_argument("--side-threads", default="1", help="stage 1's thread counts side by side, e.g. 1,2")
    a = ap.parse_args()
    try:
        side_threads = [int(x) for x in a.side_threads.split(",")]
    except ValueError:
        side_threads = []
    if not side_threads or min(side_threads) < 1 or len(set(side_threads)) < len(side_threads):
        raise SystemExit("bench_train_stages: --side-threads takes distinct counts such as 1,2, got "
                         f"{a.side_threads!r}")
    if not a.data.is_file():
        raise SystemExit(f"bench_train_stages: {a.data} is not a file")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for stage, steps in (("stage1", a.stage1_steps), ("stage2", a.stage2_steps)):
            for threads in (1, 2):
                run = tmp / f"{stage}_{threads}"
                if start(stage, threads, steps, a.data, run).wait() != 0:
                    raise SystemExit(f"bench_train_stages: {stage} on {threads} threads failed")
                out[f"{stage} alone, {threads} threads"] = round(median_after(run, a.skip), 4)
                print(json.dumps({f"{stage} alone, {threads} threads": out[f"{stage} alone, {threads} threads"]}),
                      flush=True)
        for n in side_threads:
            procs = [start("stage1", n, a.stage1_steps, a.data, tmp / f"side1_{n}"),
                     start("stage2", 1, 10 * a.stage2_steps, a.data, tmp / f"side2_{n}")]
            if procs[0].wait() != 0:
                raise SystemExit(f"bench_train_stages: stage 1 on {n} threads side by side failed")
            procs[1].terminate()
            procs[1].wait()
            end1 = sum(step_times(tmp / f"side1_{n}")[1])
            s1 = median_after(tmp / f"side1_{n}", a.skip)
            s2 = median_after(tmp / f"side2_{n}", a.skip, until=end1)
            case = {f"side by side: stage 1, {n} thread{'s' * (n > 1)}": round(s1, 4),
                    f"side by side: stage 2, 1 thread (stage 1 on {n})": round(s2, 4),
                    f"side by side: work a second (stage 1 on {n})": round(
                        out["stage1 alone, 2 threads"] / s1 + out["stage2 alone, 2 threads"] / s2, 3)}
            out.update(case)
            print(json.dumps(case), flush=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
