"""RESULTS.md's time-to-accuracy curve: ADD(-S) at 10 % of the diameter against training minutes.

    .venv/bin/python examples/linemod/curve.py runs/lm8 data/lm_test.h5 --out docs/img/time_to_accuracy.png

RUN is a two-stage run folder trained with ``--set stage2.keep_every=N`` (``detector train``), so that
``RUN/stage2/`` holds stage-2 snapshots ``step_NNNNNN.pt`` beside ``last.pt``, and ``RUN/model.pt`` exists (the
run finished). Each snapshot is put together with the run's stage 1 and the inference settings of ``RUN/model.pt``
into a model file and evaluated on LABELS (``detector eval`` with ICP; the first ``--frames`` frames). A point's
minutes are stage 1's whole training time plus stage 2's up to the snapshot, both summed from the runs'
``metrics.csv`` (the seconds of every logged step, so a resumed run counts only the time it trained), or stage
1's from ``--stage1-minutes`` where its run folder was copied without its log. For a run whose stages trained side
by side (``detector train``'s default on a CPU since 2026-12-06: stage 2's ``metrics.csv`` shows fewer threads for
its first steps; a run resumed in stage 2 after stage 1 ended is taken for one too) they overlap, so a point's minutes are the later of the two: stage 1's whole time and stage 2's up to the
snapshot (which counts its wait for stage 1). The points
are also written to ``--out`` with ``.json`` in place of the image suffix.
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
from pathlib import Path


def train_seconds(metrics: Path, upto: int | None = None) -> float:
    """Training seconds of a run up to step ``upto`` (None: all), from its metrics.csv's steps_per_s column."""
    with open(metrics, newline="") as f:
        return sum(1.0 / float(r["steps_per_s"]) for r in csv.DictReader(f)
                   if (upto is None or int(r["step"]) <= upto) and float(r["steps_per_s"]) > 0)


def side_by_side(stage2_dir: Path) -> bool:
    """Whether a stage-2 run's ``metrics.csv`` shows steps on fewer threads than others (the steps it took beside
    stage 1); runs without a threads column (before 2026-12-06) trained after stage 1."""
    with open(stage2_dir / "metrics.csv", newline="") as f:
        counts = {int(r["threads"]) for r in csv.DictReader(f) if r.get("threads")}
    return len(counts) > 1


def curve_points(run: Path, labels: Path, frames: int | None, stage1_minutes: float,
                 min_visib: float = 0.1) -> list[dict]:
    """One point per stage-2 snapshot of ``run`` (and its final weights): step, minutes, ADD(-S)@10 % without and
    with ICP (percent) on ``labels``, instances less visible than ``min_visib`` ignored (``detector eval``'s rule)."""
    from detector.checkpoint import load_checkpoint, save_two_stage
    from detector.data.frames import open_label_file
    from detector.evaluate import evaluate
    from detector.infer import checkpoint_geometry_config, checkpoint_objects, checkpoint_poser
    from detector.stage1.predictor import network_predictor
    from detector.training.checkpoint_file import read_checkpoint
    from detector.two_stage import stage_dirs

    model = read_checkpoint(run / "model.pt")
    d1, d2 = stage_dirs(run)
    stage1_part = read_checkpoint(d1 / "last.pt")
    stage1 = 60.0 * stage1_minutes
    snaps = sorted(d2.glob("step_*.pt")) + [d2 / "last.pt"]
    beside = side_by_side(d2)
    with open_label_file(labels) as lf:
        n = lf.num_frames if frames is None else min(frames, lf.num_frames)
    points, seen = [], set()
    with tempfile.TemporaryDirectory() as tmp:
        for snap in snaps:
            part = read_checkpoint(snap)["stage2"]
            if part["step"] in seen:
                continue
            seen.add(part["step"])
            path = save_two_stage(Path(tmp) / "model.pt", stage1_part,
                                  {**part, "infer_config": model["stage2"]["infer_config"],
                                   "colour_levels": model["stage2"].get("colour_levels")}, model["extra"])
            ckpt = load_checkpoint(path)
            s = evaluate(network_predictor(ckpt), labels, Path(tmp) / "report", icp=True,
                         cfg=checkpoint_geometry_config(ckpt, None, True), frames=list(range(n)),
                         poser=checkpoint_poser(ckpt, checkpoint_objects(ckpt)[0]), bop19=False,
                         min_visib=min_visib)  # ADD only
            upto = train_seconds(d2 / "metrics.csv", int(part["step"]))
            minutes = (max(stage1, upto) if beside else stage1 + upto) / 60.0
            points.append({"step": int(part["step"]), "minutes": round(minutes, 2),
                           "noicp": round(100 * s["mean"]["noicp"]["0.10"], 1),
                           "icp": round(100 * s["mean"]["icp"]["0.10"], 1)})
            print(json.dumps(points[-1]), flush=True)
    return points


def plot(points: list[dict], stage1_minutes: float, out: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4), dpi=100)
    x = [p["minutes"] for p in points]
    ax.plot(x, [p["icp"] for p in points], "D-", label="with ICP")
    ax.plot(x, [p["noicp"] for p in points], "s-", label="without refinement")
    ax.axvline(stage1_minutes, color="0.6", lw=0.8, ls="-.", label="stage 1 done")
    ax.axhline(90, color="0.7", lw=0.8, ls="--")
    ax.axvline(60, color="0.7", lw=0.8, ls=":")
    ax.set(xlabel="training minutes (2-core CPU, both stages)", ylabel="ADD(-S) at 10 % of the diameter (%)",
           ylim=(0, 100), xlim=(0, max(65.0, max(x) + 3)), title=title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="two-stage run folder trained with --set stage2.keep_every=N")
    ap.add_argument("labels", type=Path, help="label file to evaluate on (argen label)")
    ap.add_argument("--out", type=Path, required=True, help="the plot (.png); the points go to the same name .json")
    ap.add_argument("--frames", type=int, default=None, help="evaluate only the first N frames")
    ap.add_argument("--min-visib", type=float, default=0.1,
                    help="ignore instances less visible than this (detector eval's --min-visib; default 0.1)")
    ap.add_argument("--stage1-minutes", type=float, default=None,
                    help="stage 1's training minutes (default: summed from RUN/stage1/metrics.csv)")
    a = ap.parse_args()
    from detector.two_stage import stage_dirs

    log = stage_dirs(a.run)[0] / "metrics.csv"
    if a.stage1_minutes is None and not log.is_file():
        raise SystemExit(f"curve.py: {log} is missing; give --stage1-minutes")
    stage1 = a.stage1_minutes if a.stage1_minutes is not None else train_seconds(log) / 60.0
    points = curve_points(a.run, a.labels, a.frames, stage1, a.min_visib)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.with_suffix(".json").write_text(json.dumps(points, indent=1) + "\n")
    plot(points, stage1, a.out, f"two-stage model on {a.labels.name}")


if __name__ == "__main__":
    main()
