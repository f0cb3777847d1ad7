"""Evaluation report files: report.md (tables laid out like the paper's Tables II and III, and BOP19's Average
Recall), report.json, curve.png (accuracy against threshold), the BOP results CSV and scores_bop19.json.

The BOP CSV is a BOP boundary: there, and only there, translations are millimetres (BOP convention).
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
from pathlib import Path

import numpy as np

from argen.fileio import atomic_path
from detector.errors import DetectorError
from detector.evaluation.metrics import THRESHOLDS

BOP_FIELDS = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time")
STAGES = ("sampling", "network", "voting", "kabsch", "stage2", "icp", "depth_check", "colour_check", "part_check",
          "continuation_check")


def file_identity(path: str | Path) -> dict:
    """How a report names a file it was made from: {"path": as given, "bytes": its size, "sha256": its digest}. The
    digest, not the time it was written: a label file or model made again with the same bytes is the same input."""
    p = Path(path)
    h = hashlib.sha256()
    with p.open("rb") as f:  # in 1 MiB pieces (hashlib.file_digest is Python 3.11's; the project runs on 3.10)
        for piece in iter(lambda: f.read(1 << 20), b""):
            h.update(piece)
    return {"path": str(path), "bytes": p.stat().st_size, "sha256": h.hexdigest()}


def run_record(model: str | Path | None, labels: str | Path, **options) -> dict:
    """What made a report besides its settings (``config``, ``sampling``, ``infer``): the model file and the label
    file (:func:`file_identity`; model None: no model, an oracle evaluation) and the evaluation's other options
    (seed, visibility threshold, frames...), JSON values."""
    return {"model": None if model is None else file_identity(model), "labels": file_identity(labels), **options}


def networks_in(net_dtype: str | None) -> str:
    """The words after "frames per second on DEVICE" for the networks' number format (None: not recorded)."""
    return f", the networks in {net_dtype}" if net_dtype else ""


#: The report.json entries that say how a report was made: equal in two reports, the same evaluation made them.
MADE_BY = ("run", "icp", "config", "sampling", "infer")


def previous_report(out_dir: str | Path) -> dict:
    """The report.json in ``out_dir`` as a dict; {} where there is none or it cannot be read (it is made again)."""
    try:
        report = json.loads((Path(out_dir) / "report.json").read_text())
    except (OSError, ValueError):
        return {}
    return report if isinstance(report, dict) else {}


def made_alike(report: dict, made_by: dict) -> bool:
    """Whether ``report`` (a report.json's contents) was made as ``made_by`` says (:data:`MADE_BY` entries, as the
    evaluation about to run would record them): a report written before reports recorded their ``run`` never is.
    Model and label files count by their digests, not by their paths."""
    def key(d: dict) -> str:
        d = json.loads(json.dumps({k: d.get(k) for k in MADE_BY}))
        for f in ("model", "labels"):
            if isinstance(d["run"], dict) and isinstance(d["run"].get(f), dict):
                d["run"][f].pop("path", None)
        return json.dumps(d, sort_keys=True)
    return isinstance(report.get("run"), dict) and key(report) == key(made_by)


def bop_row(scene_id: int, im_id: int, obj_id: int, score: float, R: np.ndarray, t: np.ndarray, time_s: float) -> dict:
    """One BOP results row: R (3,3) row-major as 9 space-separated values, t (3,) metres -> millimetres, time seconds."""
    return {"scene_id": int(scene_id), "im_id": int(im_id), "obj_id": int(obj_id), "score": f"{float(score):.6f}",
            "R": " ".join(f"{v:.8f}" for v in np.asarray(R, np.float64).reshape(9)),
            "t": " ".join(f"{v:.4f}" for v in np.asarray(t, np.float64).reshape(3) * 1000.0),  # BOP: mm
            "time": f"{float(time_s):.6f}"}


def bop_csv_name(method: str, dataset: str, split: str) -> str:
    """The BOP results file name ``METHOD_DATASET-SPLIT[-SPLITTYPE].csv`` (the BOP toolkit's convention).

    method, dataset: letters and digits only (BOP parses the name at ``_`` and ``-``); split: a BOP split folder
    name such as ``test`` or ``train_pbr`` (written as ``train-pbr``: split ``train``, split type ``pbr``).
    A name part the toolkit could not parse back is a DetectorError.
    """
    parts = split.split("_")
    for what, v in [("method", method), ("dataset name", dataset)] + [("split", x) for x in parts]:
        if not v or not v.isalnum():
            raise DetectorError(f"BOP results file: the {what} '{v}' must be letters and digits only "
                                "(no '_' or '-': BOP splits the file name there)")
    if len(parts) > 2:
        raise DetectorError(f"BOP results file: split '{split}' has more than a split and a split type")
    return f"{method}_{dataset}-{'-'.join(parts)}.csv"


def parse_bop_csv_name(name: str) -> dict[str, str | None]:
    """The parts of a BOP results file name: {"method", "dataset", "split", "split_type"} (split_type None when
    absent), read the way the BOP toolkit reads them. A name it could not parse is a ValueError."""
    stem = Path(name).name
    if not stem.endswith(".csv") or stem.count("_") != 1:
        raise ValueError(f"not a BOP results file name: {name}")
    method, rest = stem[:-4].split("_")
    info = rest.split("-")
    if len(info) not in (2, 3) or not method or not all(info):
        raise ValueError(f"not a BOP results file name: {name}")
    return {"method": method, "dataset": info[0], "split": info[1], "split_type": info[2] if len(info) == 3 else None}


def default_dataset_name(source_dataset: str) -> str:
    """A BOP dataset name from a label file's source dataset folder: its name with everything but letters and
    digits removed (``data/lm_test`` -> ``lmtest``); ``argen`` when nothing is left."""
    name = "".join(c for c in Path(str(source_dataset)).name if c.isalnum())
    return name or "argen"


def write_bop_csv(path: Path, rows: list[dict]) -> Path:
    """Write BOP results rows (see :func:`bop_row`) with the BOP header."""
    path = Path(path)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=BOP_FIELDS, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
    return path


def parse_bop_row(r: dict) -> dict:
    """One BOP results row as written (:func:`bop_row`) or read from the CSV, parsed: R (3,3) float64, t (3,) metres,
    ids int, score and time float - exactly the values the file carries."""
    return {"scene_id": int(r["scene_id"]), "im_id": int(r["im_id"]), "obj_id": int(r["obj_id"]),
            "score": float(r["score"]), "R": np.array(str(r["R"]).split(), float).reshape(3, 3),
            "t": np.array(str(r["t"]).split(), float) / 1000.0, "time": float(r["time"])}


def read_bop_csv(path: Path) -> list[dict]:
    """Read a BOP results CSV back: R (3,3) float64, t (3,) metres, ids int, score and time float."""
    with Path(path).open() as f:
        return [parse_bop_row(r) for r in csv.DictReader(f)]


def _pct(v) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{100 * v:.1f}"


def _clustering(cfg: dict) -> str:
    """How centre votes became instances: density modes (``mode_radius`` > 0) or touching voxels of ``cell``."""
    if cfg.get("mode_radius", 0) > 0:
        return f"votes clustered at density modes within {cfg['mode_radius']:g} of the diameter"
    return f"votes clustered in touching {cfg['cell'] * 100:.1f} cm voxels"


def markdown(summary: dict) -> str:
    """The report as Markdown: Table II (ADD at 10 % without / with ICP), Table III (10/15/30 %), F1, timings."""
    objs = summary["objects"]
    icp = summary["icp"]
    lines = [f"# Evaluation of `{summary['label_file']}`", "",
             f"{summary['num_frames']} frames, tau {summary['config']['tau']}, {_clustering(summary['config'])}. "
             "Metric: ADD (ADD-S for symmetric objects, marked *); "
             "a pose is correct under the given share of the object diameter. Per object and frame only the k "
             "best-scoring poses count, k its instances, matched greedily by score (BOP19's rule: what a user reads).",
             "",
             "## ADD accuracy at 10 % of the diameter (Table II layout)", "",
             "| object | instances | w/o refinement | with ICP |", "|---|---:|---:|---:|"]
    for o in objs:
        lines.append(f"| {o['name']}{'*' if o['symmetric'] else ''} | {o['num_gt']} | {_pct(o['add']['noicp']['0.10'])}"
                     f" | {_pct(o['add']['icp']['0.10']) if icp else '–'} |")
    m = summary["mean"]
    lines += [f"| **average** | {sum(o['num_gt'] for o in objs)} | **{_pct(m['noicp']['0.10'])}** | "
              f"**{_pct(m['icp']['0.10']) if icp else '–'}** |", "",
              "## ADD accuracy at several thresholds, without refinement (Table III layout)", "",
              "| object | " + " | ".join(f"{int(k * 100)} %" for k in THRESHOLDS) + " |",
              "|---|" + "---:|" * len(THRESHOLDS)]
    for o in objs:
        lines.append(f"| {o['name']} | " + " | ".join(_pct(o["add"]["noicp"][f"{k:.2f}"]) for k in THRESHOLDS) + " |")
    lines += ["| **average** | " + " | ".join(f"**{_pct(m['noicp'][f'{k:.2f}'])}**" for k in THRESHOLDS) + " |", "",
              "## Detection at 15 % of the diameter (LC-HF protocol: greedy by score, each instance once)", "",
              "| object | detections | instances | precision | recall | F1 |", "|---|---:|---:|---:|---:|---:|"]
    key = "icp" if icp else "noicp"
    for o in objs:
        f = o["f1"][key]
        lines.append(f"| {o['name']} | {f['num_det']} | {f['num_gt']} | {_pct(f['precision'])} | {_pct(f['recall'])}"
                     f" | {_pct(f['f1'])} |")
    f = summary["f1"][key]
    lines += [f"| **all** | {f['num_det']} | {f['num_gt']} | {_pct(f['precision'])} | {_pct(f['recall'])} | "
              f"**{_pct(f['f1'])}** |", "", f"(poses {'with' if icp else 'without'} ICP)", ""]
    lines += bop19_markdown(summary)
    r = summary.get("icp_refinement")
    if r:
        n = sum(r.values())
        lines += [f"ICP refinement: {r['accepted']} of {n} detections took the ICP pose; {r['rejected']} kept their "
                  f"unrefined pose because ICP did not improve the trimmed point-to-plane fit; {r['skipped']} had too "
                  "few points for ICP.", ""]
    lines += ["## Time per frame", "", "| stage | ms |", "|---|---:|"]
    for s in STAGES:
        if s in summary["timing_ms"]:
            lines.append(f"| {s} | {summary['timing_ms'][s]:.1f} |")
    lines += [f"| **total** | **{summary['timing_ms']['total']:.1f}** |", "",
              f"{summary['fps']:.2f} frames per second on {summary.get('device', 'cpu')}"
              f"{networks_in((summary.get('run') or {}).get('net_dtype'))}.", "",
              "Files: `report.json` (all numbers), `curve.png` (accuracy against threshold), "
              f"`{summary['bop_csv']}` (BOP results; R row-major, t in millimetres).", ""]
    return "\n".join(lines)


def _ar(v) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.3f}"


def bop19_markdown(summary: dict) -> list[str]:
    """The report's BOP19 section: per object and over all targets, the recalls of VSD, MSSD and MSPD averaged over
    their thresholds and their mean, AR (or why they were not computed)."""
    b = summary.get("bop19") or {"skipped": "not computed"}
    head = ["## BOP19 Average Recall (the BOP benchmark's score)", ""]
    if "skipped" in b:
        return head + [f"Not computed: {b['skipped']}.", ""]
    names = {int(o["obj_id"]): o["name"] for o in summary["objects"]}
    lines = head + ["| object | targets | VSD | MSSD | MSPD | AR |", "|---|---:|---:|---:|---:|---:|"]
    for oid, o in sorted(((int(k), v) for k, v in b["objects"].items())):
        lines.append(f"| {names.get(oid, oid)} | {o['num_targets']} | {_ar(o['vsd'])} | {_ar(o['mssd'])} | "
                     f"{_ar(o['mspd'])} | {_ar(o['ar'])} |")
    lines += [f"| **all** | {b['num_targets']} | {_ar(b['bop19_average_recall_vsd'])} | "
              f"{_ar(b['bop19_average_recall_mssd'])} | {_ar(b['bop19_average_recall_mspd'])} | "
              f"**{_ar(b['bop19_average_recall'])}** |", "",
              f"The poses of `{summary['bop_csv']}` on `{b['dataset']}` ({b['split']}), as BOP's toolkit scores them "
              f"(`scores_bop19.json` has its keys): targets from {b['targets']}, those of the {b['num_images']} "
              "evaluated images; per object and image only as many poses as it has targets, best score first, "
              "matched greedily by score; VSD (delta 15 mm, tau 0.05-0.5 of the diameter), MSSD (0.05-0.5 of the "
              "diameter) and MSPD (5-50 px x width / 640) recalls averaged over their thresholds; AR is their mean. "
              "**all** pools the targets, so it is not the mean of the rows.", ""]
    name = b.get("toolkit_dataset")
    lines += [f"BOP toolkit check, unmodified: link `{b['dataset']}` as `$BOP_PATH/{name}`, set `BOP_RESULTS_PATH` to "
              f"this folder and run `scripts/eval_bop19_pose.py --result_filenames {summary['bop_csv']}` (README, "
              "\"Using argen data with the BOP toolkit\")." if name else
              "The BOP toolkit needs an entry for this dataset's name before it can score this file (README, \"Using "
              "argen data with the BOP toolkit\").", ""]
    return lines


def plot_curve(curves: dict[str, tuple[np.ndarray, np.ndarray]], path: Path) -> Path:
    """Accuracy (0..1) against threshold (fraction of the diameter) per named curve, as a PNG."""
    # lazy: matplotlib loads slowly; only the curve plot needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after choosing the Agg backend

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for name, (ks, acc) in curves.items():
        ax.plot(100 * np.asarray(ks), 100 * np.asarray(acc), label=name)
    for k in THRESHOLDS:
        ax.axvline(100 * k, color="0.8", lw=0.8, zorder=0)
    ax.set(xlabel="threshold (% of diameter)", ylabel="ADD accuracy (%)", ylim=(0, 101), xlim=(0, 50))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def json_safe(value):
    """``value`` with NaN/inf floats (and numpy scalars/arrays) made strict-JSON friendly (None, plain lists)."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_report(out_dir: Path, summary: dict, curves: dict, bop_rows: list[dict]) -> dict[str, Path]:
    """Write report.md, report.json, curve.png, the BOP CSV (``summary['bop_csv']``) and, when summary["bop19"]
    holds the scores, scores_bop19.json (the BOP toolkit's keys) into ``out_dir``. report.json, which says how the
    report was made (``detector eval --reuse`` reads it), goes first from the folder and comes back last, whole (a
    temporary file renamed): a run killed while writing leaves no report.json beside the other files."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"md": out_dir / "report.md", "json": out_dir / "report.json", "curve": out_dir / "curve.png",
             "bop": out_dir / summary["bop_csv"]}
    paths["json"].unlink(missing_ok=True)
    text = json.dumps(json_safe(summary), indent=2, allow_nan=False) + "\n"  # a summary it cannot write: before
    paths["md"].write_text(markdown(summary))
    b = summary.get("bop19") or {}
    if "skipped" not in b and b:
        paths["bop19"] = out_dir / "scores_bop19.json"
        paths["bop19"].write_text(json.dumps(json_safe({k: v for k, v in b.items() if k.startswith("bop19_")}),
                                             indent=2, allow_nan=False) + "\n")
    else:  # not scored this time: no figures of an earlier run may stay beside this report
        (out_dir / "scores_bop19.json").unlink(missing_ok=True)
    plot_curve(curves, paths["curve"])
    write_bop_csv(paths["bop"], bop_rows)
    with atomic_path(paths["json"]) as tmp:
        tmp.write_text(text)
    return paths
