"""`detector eval`: scoring only. Runs a predictor (:mod:`detector.infer`) over a label file, matches the poses
to the ground truth (:mod:`detector.evaluation.metrics`: ADD, ADD-S, F1), scores the BOP results file on the labelled BOP
dataset (:mod:`detector.evaluation.bop_eval`: BOP19 Average Recall) and writes the report (:mod:`detector.report`).
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, is_dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from argen.h5 import LabelFile
from detector.errors import DetectorError
from detector.evaluation.bop_eval import dataset_pixel_centres, score_bop19, toolkit_dataset_name
from detector.evaluation.metrics import THRESHOLDS, accuracy, accuracy_curve, match_frame, pose_error, prf
from detector.geometry.icp import icp_counts
from detector.geometry.types import Detection, GeometryConfig, ObjectInfo
from detector.infer import estimate
from detector.report import STAGES, bop_csv_name, bop_row, default_dataset_name, parse_bop_row, write_report
from detector.stage1.predictor import Predictor

#: The default method name of the BOP results file (``METHOD_DATASET-SPLIT.csv``).
METHOD = "argen"


def error_matrix(dets: list[Detection], frame, table) -> np.ndarray:
    """(D,G) pose errors, metres (ADD, or ADD-S for symmetric objects); inf between different objects."""
    inst = frame.instances
    err = np.full((len(dets), len(inst)), np.inf)
    for d, det in enumerate(dets):
        for g in np.flatnonzero(inst.obj_id == det.obj_id):
            m = table.index(int(det.obj_id))
            err[d, g] = pose_error(table.model_points[m], bool(table.symmetric[m]), inst.R[g], inst.t[g], det.R, det.t)
    return err


def _summary_for(rows: list[dict], key: str, k_list=THRESHOLDS) -> dict:
    errs = np.array([r[key] for r in rows], np.float64)
    dia = np.array([r["diameter"] for r in rows], np.float64)
    return {f"{k:.2f}": accuracy(errs, dia, k) for k in k_list}


def evaluate(predictor: Predictor, label_path: str | Path, out_dir: str | Path, icp: bool = False,
             cfg: GeometryConfig | None = None, frames: list[int] | None = None, min_visib: float = 0.1,
             device: str = "cpu", progress: bool = False, poser=None, method: str = METHOD,
             dataset_name: str | None = None, bop_dataset: str | Path | None = None, bop19: bool = True,
             sampling: dict | None = None, objects: ObjectInfo | None = None, run: dict | None = None) -> dict:
    """Evaluate ``predictor`` on a label file and write the report into ``out_dir``.

    objects: what the inference knows of the objects (a model's: :func:`detector.infer.checkpoint_objects`, with the
    part symmetries its stage 2 was taught under); None: the label file's object table. Poses are scored against
    the label file's either way.
    Ground-truth instances with ``visib_fract < min_visib`` are ignored (neither missed nor matched). poser: a
    two-stage model's stage 2 (see :func:`estimate`). The BOP results file is ``METHOD_DATASET-SPLIT.csv``
    (:func:`detector.report.bop_csv_name`): ``method``, ``dataset_name`` (default: the BOP toolkit's name for a
    capture with one of its datasets' objects and image size, :func:`detector.evaluation.bop_eval.toolkit_dataset_name`, such as
    ``lmo`` for the 8 LM-O objects, so the toolkit runs on it unmodified; else the label file's source dataset folder
    name, letters and digits only) and the label file's source split.
    BOP19 Average Recall (``bop19``): the BOP CSV's poses scored on the BOP dataset the label file was made from
    (``bop_dataset``, default the label file's source dataset), the targets of the evaluated images only; skipped
    with the reason in summary["bop19"]["skipped"] when that folder is gone or cannot be scored. sampling: how the
    predictor's network sampled a frame (e.g. ``{"density": 1.0, "passes": 2, "points": 4096, "keypoints": 1024}``:
    points and keypoints of each pass), recorded
    as summary["sampling"] (None: not recorded). A stage 2's inference settings (the ``cfg`` of a
    :class:`detector.stage2.poser.CropPoser` ``poser``) are recorded as summary["infer"] (None: none, or a poser
    that does not carry them). run: what else made the report (the model file, the label file, the seed...:
    :func:`detector.report.run_record`), recorded as summary["run"].
    Returns the summary written to report.json (per-object ADD accuracies at 10/15/30 % without and with ICP,
    F1 at 15 %, mean ms per stage, fps, and with ICP how many detections had their ICP pose accepted, rejected
    (it did not fit better, so the unrefined pose was kept) or skipped (too few points): "icp_refinement"; "bop19":
    the four BOP19 figures, per object, or "skipped").
    """
    if bop_dataset is not None and not Path(bop_dataset).is_dir():
        raise DetectorError(f"--bop-dataset {bop_dataset} is not a folder")
    cfg = replace(cfg or GeometryConfig(), icp=icp)
    keys = ("noicp", "icp") if icp else ("noicp",)
    gt_rows, bop_rows, counts, times = [], [], {}, []
    icp_status = {"accepted": 0, "rejected": 0, "skipped": 0}
    images: set[tuple[int, int]] = set()
    with LabelFile(label_path) as lf:
        split = str(lf.attrs.get("source_split") or "test")
        root = scored_dataset(lf, bop_dataset)
        toolkit_name = toolkit_dataset_name(root, split) if root else None
        csv_name = bop_csv_name(method, dataset_name or toolkit_name or default_dataset_name(
            lf.attrs.get("source_dataset", "")), split)
        table = lf.objects
        source = (root, split, str(lf.attrs.get("source_argen_json") or ""))
        in_file = ObjectInfo.from_table(table)
        lacking = "the label file does not carry" if objects is None else \
            "neither the model nor the label file carries"  # an oracle evaluation has no model
        if objects is None:
            objects = in_file
        else:  # a model trained before its table carried surface normals takes the label file's, of the same meshes
            objects.take_surfaces(in_file)
        if cfg.continuation_check and not objects.surfaces:
            print(f"warning: geometry.continuation_check is on, but {lacking} the "
                  "objects' surface normals (label files written before 2026-12-07): nothing is checked",
                  file=sys.stderr)
        idx = range(lf.num_frames) if frames is None else frames
        it = idx
        if progress:
            it = tqdm(idx, desc="eval", unit="frame")
        for i in it:
            frame = lf.frame(i)
            t0 = time.perf_counter()
            preds = predictor(frame)
            timings = dict(preds.timings)
            res = dict(zip(("noicp", "icp"), estimate(preds, objects, cfg, timings, frame.features[:, :3], poser,
                                                      frame.features, check_unrefined=True)))
            frame_time = time.perf_counter() - t0
            timings["total"] = frame_time
            times.append(timings)
            inst = frame.instances
            valid = np.asarray(inst.visib_fract) >= min_visib
            dia = np.array([table.diameters[table.index(int(o))] for o in inst.obj_id], np.float64)
            per_key = {}
            for key in keys:
                dets = res[key]
                err = error_matrix(dets, frame, table)
                scores = np.array([d.score for d in dets])
                for oid in set(inst.obj_id.tolist()) | {d.obj_id for d in dets}:
                    sel_d = np.array([d.obj_id == oid for d in dets], bool)
                    sel_g = inst.obj_id == oid
                    m = match_frame(scores[sel_d], err[np.ix_(sel_d, sel_g)], dia[sel_g], valid[sel_g])
                    c = counts.setdefault((key, int(oid)), [0, 0, 0])
                    c[0], c[1], c[2] = c[0] + m.tp, c[1] + m.num_det, c[2] + m.num_gt
                    per_key.setdefault(int(oid), []).append((m.gt_error, np.flatnonzero(sel_g)))
            for g in np.flatnonzero(valid):
                row = {"frame": int(i), "scene_id": int(frame.scene_id), "im_id": int(frame.im_id),
                       "obj_id": int(inst.obj_id[g]), "diameter": float(dia[g])}
                for key, (gt_err, cols) in zip(keys, per_key[int(inst.obj_id[g])]):
                    row[key] = float(gt_err[np.searchsorted(cols, g)])
                gt_rows.append(row)
            final = res["icp"] if icp else res["noicp"]
            if icp:
                for k, v in icp_counts(final).items():
                    icp_status[k] += v
            bop_rows += [bop_row(frame.scene_id, frame.im_id, d.obj_id, d.score, d.R, d.t, frame_time) for d in final]
            images.add((int(frame.scene_id), int(frame.im_id)))
        num_frames = len(idx)
    scores = bop19_summary(bop_rows, images, *source, progress) if bop19 else {"skipped": "not asked for"}
    if "skipped" not in scores:  # how the official toolkit can check these figures (report.md says it)
        scores["toolkit_dataset"] = toolkit_name if csv_name.split("_", 1)[1].startswith(f"{toolkit_name}-") else None
    return _finish(gt_rows, counts, times, table, keys, str(label_path), num_frames, bop_rows, out_dir,
                   device, icp_status if icp else None, csv_name, scores,
                   report_settings(cfg, icp, sampling, poser, run))


def scored_dataset(label_file: LabelFile, bop_dataset: str | Path | None = None) -> str | Path | None:
    """The BOP dataset folder whose targets BOP19 AR is scored on: ``bop_dataset`` where given, else the one the open
    ``label_file`` was made from (None: neither names one)."""
    return bop_dataset or label_file.attrs.get("source_dataset") or None


def report_settings(cfg: GeometryConfig | None, icp: bool, sampling: dict | None, poser, run: dict | None) -> dict:
    """The report.json entries that say how :func:`evaluate` with these arguments makes its report
    (:data:`detector.report.MADE_BY`), as it records them: ``detector eval --reuse`` compares them with a report's.
    A non-finite setting is recorded by its name ("inf", "-inf", "nan"): JSON has no number for it, and it must not
    read back as None, which several settings take to mean something else."""
    def named(d: dict | None) -> dict | None:
        if d is None:
            return None
        return {k: (str(v) if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}

    return {"run": run, "icp": icp, "config": named(asdict(replace(cfg or GeometryConfig(), icp=icp))),
            "sampling": named(sampling),
            "infer": named(asdict(poser.cfg)) if is_dataclass(getattr(poser, "cfg", None)) else None}


def bop19_summary(bop_rows: list[dict], images: set[tuple[int, int]], root, split: str, argen_json: str = "",
                  progress: bool = False) -> dict:
    """BOP19 Average Recall of BOP results rows (:func:`detector.report.bop_row`) on the BOP dataset at ``root``, the
    targets of ``images`` ((scene_id, im_id)) only: the toolkit's four figures and its average time per image (s; -1
    without estimates), per object, the dataset, split and pixel-centre convention; {"skipped": reason} when
    ``root`` is not a folder or cannot be scored (a DetectorError: the ADD report stays)."""
    if not root or not Path(root).is_dir():
        return {"skipped": f"the BOP dataset folder {root} is not there (give --bop-dataset)"}
    rows = [parse_bop_row(r) for r in bop_rows]
    times = {(r["scene_id"], r["im_id"]): r["time"] for r in rows}
    try:
        pc = dataset_pixel_centres(argen_json)
        res = score_bop19(root, split, rows, images, pc, progress)
    except DetectorError as exc:
        return {"skipped": str(exc)}
    res.pop("errors")
    res["bop19_average_time_per_image"] = float(np.mean(list(times.values()))) if times else -1.0
    return {**res, "dataset": str(root), "split": split, "pixel_centres": pc}


def _finish(gt_rows, counts, times, table, keys, label_file, num_frames, bop_rows, out_dir, device,
            icp_status=None, csv_name="argen_argen-test.csv", bop19=None, settings=None) -> dict:
    """Aggregate per-instance rows into the summary, write the report files and return the summary."""
    objs, curves = [], {}
    for m, oid in enumerate(table.ids.tolist()):
        rows = [r for r in gt_rows if r["obj_id"] == oid]
        if not rows and not any(counts.get((k, oid), [0, 0])[1] for k in keys):
            continue
        o = {"obj_id": oid, "name": table.names[m], "symmetric": bool(table.symmetric[m]),
             "diameter": float(table.diameters[m]), "num_gt": len(rows),
             "add": {k: (_summary_for(rows, k) if k in keys else None) for k in ("noicp", "icp")},
             "f1": {}}
        for k in ("noicp", "icp"):
            tp, nd, ng = counts.get((k, oid), [0, 0, 0])
            o["f1"][k] = {**prf(tp, nd, ng), "num_det": nd, "num_gt": ng} if k in keys else None
        objs.append(o)
    mean, f1 = {}, {}
    for k in ("noicp", "icp"):
        if k not in keys:
            mean[k], f1[k] = None, None
            continue
        with_gt = [o for o in objs if o["num_gt"]]
        mean[k] = {f"{t:.2f}": float(np.mean([o["add"][k][f"{t:.2f}"] for o in with_gt])) if with_gt else float("nan")
                   for t in THRESHOLDS}
        tp, nd, ng = (sum(counts.get((k, o["obj_id"]), [0, 0, 0])[j] for o in objs) for j in range(3))
        f1[k] = {**prf(tp, nd, ng), "num_det": nd, "num_gt": ng}
        errs = np.array([r[k] for r in gt_rows], np.float64)
        dia = np.array([r["diameter"] for r in gt_rows], np.float64)
        curves["with ICP" if k == "icp" else "without refinement"] = accuracy_curve(errs, dia)
    stages = [s for s in STAGES if any(s in t for t in times)]
    timing_ms = {s: 1000 * float(np.mean([t.get(s, 0.0) for t in times])) if times else 0.0 for s in stages}
    timing_ms["total"] = 1000 * float(np.mean([t["total"] for t in times])) if times else 0.0
    summary = {"label_file": label_file, "num_frames": num_frames, **settings,
               "objects": objs, "mean": mean, "f1": f1, "timing_ms": timing_ms,
               "fps": 1000.0 / timing_ms["total"] if timing_ms["total"] > 0 else float("inf"),
               "device": device, "bop_csv": csv_name, "icp_refinement": icp_status,
               "bop19": bop19 or {"skipped": "not computed"}, "instances": gt_rows,
               "curve": {name: {"k": ks.tolist(), "accuracy": acc.tolist()} for name, (ks, acc) in curves.items()}}
    write_report(Path(out_dir), summary, curves, bop_rows)
    return summary
