"""`detector eval`: run a predictor over a label file, poses through :mod:`detector.pose`, score and report.

A predictor maps one frame (anything with ``features`` (N,9); the evaluation passes ``argen.h5.FrameLabels``)
to :class:`Predictions`. :func:`oracle_predictor` uses the file's ground-truth labels instead of a network
(checks the whole pose stage); :func:`network_predictor` runs a checkpoint's PoseNet on CPU or GPU.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from detector.metrics import THRESHOLDS, accuracy, accuracy_curve, match_frame, pose_error, prf
from detector.pose import Detection, ObjectInfo, PoseConfig, detect, icp_counts, nms, refine
from detector.report import STAGES, bop_csv_name, bop_row, default_dataset_name, write_report

#: The default method name of the BOP results file (``METHOD_DATASET-SPLIT.csv``).
METHOD = "argen"


@dataclass
class Predictions:
    """Per-point predictions for one frame (K points).

    xyz: (K,3) float metres; class_probs: (K,C+1) float, column 0 background, column c object ``class_ids[c-1]``;
    class_ids: C object ids; control_points: (K,9,3) float metres (point + offsets); confidence: (K,) in [0,1];
    point_index: (K,) int64 input row of each point; timings: seconds spent, e.g. {"sampling", "network"}.
    """

    xyz: np.ndarray
    class_probs: np.ndarray
    class_ids: list[int]
    control_points: np.ndarray
    confidence: np.ndarray
    point_index: np.ndarray
    timings: dict = field(default_factory=dict)

    @property
    def obj_ids(self) -> np.ndarray:
        """(K,) int64 object id of each point's most likely class, 0 = background."""
        lut = np.concatenate([[0], np.asarray(self.class_ids, np.int64)])
        return lut[np.argmax(self.class_probs, axis=1)]


Predictor = Callable[[object], Predictions]


def oracle_predictor(num_points: int | None = None, seed: int = 0) -> Predictor:
    """A predictor that returns the frame's ground truth: class = semantic label, control points = the per-point
    labels, confidence 1. num_points: sample that many rows per frame (seeded) like the network; None = all."""

    def predict(frame) -> Predictions:
        n = len(frame.features)
        rows = np.arange(n) if num_points is None or num_points >= n else \
            np.sort(np.random.default_rng([seed, frame.scene_id, frame.im_id]).choice(n, num_points, replace=False))
        ids = sorted(set(np.unique(frame.semantic).tolist()) - {0})
        cls = np.searchsorted(ids, frame.semantic[rows]) + 1
        cls[frame.semantic[rows] == 0] = 0
        probs = np.eye(len(ids) + 1, dtype=np.float32)[cls]
        return Predictions(frame.features[rows, :3].astype(np.float64), probs, ids,
                           frame.control_points[rows].astype(np.float64), np.ones(len(rows)), rows.astype(np.int64))

    return predict


def network_predictor(checkpoint, seed: int = 0, device: str | None = None) -> Predictor:
    """A predictor running ``checkpoint.model`` (a :class:`detector.checkpoint.Checkpoint`) on one frame.

    Sampling and neighbour indices as in training (``detector.data.inference_batch``); times "sampling" and
    "network" (synchronised on GPU). On a GPU the neighbour indices are computed by the model (inside "network").
    """
    import torch

    from detector.data import inference_batch

    model = checkpoint.model
    dev = torch.device(device) if device else next(model.parameters()).device
    model.to(dev).eval()

    def predict(frame) -> Predictions:
        t0 = time.perf_counter()
        batch = inference_batch(frame.features, checkpoint.model_config, checkpoint.num_points, seed,
                                normalisation=checkpoint.normalisation or None, precompute=dev.type == "cpu")
        feats = batch.pop("features").to(dev)
        rows = batch.pop("point_index").numpy()
        indices = {k: v.to(dev) for k, v in batch.items()}
        t1 = time.perf_counter()
        with torch.no_grad():
            out = model(feats, indices or None)
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
        t2 = time.perf_counter()
        kp = out["keypoints"][0].cpu().numpy()
        xyz = np.asarray(frame.features, np.float64)[rows[kp], :3]  # metres, exactly the input points
        offsets = out["offsets"][0].double().cpu().numpy()
        return Predictions(xyz, torch.softmax(out["logits"][0].float(), -1).cpu().numpy(), list(checkpoint.class_ids),
                           xyz[:, None, :] + offsets, out["confidence"][0].double().cpu().numpy(), rows[kp],
                           {"sampling": t1 - t0, "network": t2 - t1})

    return predict


def estimate(preds: Predictions, objects: ObjectInfo, cfg: PoseConfig, timings: dict | None = None,
             cloud: np.ndarray | None = None, poser=None, features: np.ndarray | None = None
             ) -> tuple[list[Detection], list[Detection] | None]:
    """Detections of one frame without and (when ``cfg.icp``) with ICP refinement; stage seconds into ``timings``.

    cloud: (M,3) metres, the frame's full point cloud, for ICP (see :func:`detector.pose.refine`); None: the
    predicted points only. poser: a two-stage model's stage 2 (:class:`detector.infer.CropPoser`), called with
    the stage-1 detections and ``features`` (M,9), the frame's points whose xyz is ``cloud``; its detections are
    suppressed again (two crops may settle on one object). ``cfg.min_score`` then drops the weak refined
    detections (by their score after ICP, recomputed there for a two-stage detection) and
    ``cfg.min_score_unrefined`` the weak unrefined ones.
    """
    dets = detect(preds.xyz, preds.obj_ids, preds.confidence, preds.control_points, objects, cfg, timings)
    if poser is not None:
        dets = nms(poser(dets, features, timings), objects.diameters, cfg.nms_fraction)
    refined = refine(dets, preds.xyz, objects, cfg, timings, cloud) if cfg.icp else None
    lo = cfg.min_score if cfg.min_score_unrefined is None else cfg.min_score_unrefined
    return ([d for d in dets if d.score >= lo],
            [d for d in refined if d.score >= cfg.min_score] if refined is not None else None)


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
             cfg: PoseConfig | None = None, frames: list[int] | None = None, min_visib: float = 0.1,
             device: str = "cpu", progress: bool = False, poser=None, method: str = METHOD,
             dataset_name: str | None = None) -> dict:
    """Evaluate ``predictor`` on a label file and write the report into ``out_dir``.

    Ground-truth instances with ``visib_fract < min_visib`` are ignored (neither missed nor matched). poser: a
    two-stage model's stage 2 (see :func:`estimate`). The BOP results file is ``METHOD_DATASET-SPLIT.csv``
    (:func:`detector.report.bop_csv_name`): ``method``, ``dataset_name`` (default: the label file's source dataset
    folder name, letters and digits only) and the label file's source split.
    Returns the summary written to report.json (per-object ADD accuracies at 10/15/30 % without and with ICP,
    F1 at 15 %, mean ms per stage, fps, and with ICP how many detections had their ICP pose accepted, rejected
    (it did not fit better, so the unrefined pose was kept) or skipped (too few points): "icp_refinement").
    """
    from argen.h5 import LabelFile

    cfg = replace(cfg or PoseConfig(), icp=icp)
    keys = ("noicp", "icp") if icp else ("noicp",)
    gt_rows, bop_rows, counts, times = [], [], {}, []
    icp_status = {"accepted": 0, "rejected": 0, "skipped": 0}
    with LabelFile(label_path) as lf:
        csv_name = bop_csv_name(method, dataset_name or default_dataset_name(lf.attrs.get("source_dataset", "")),
                                str(lf.attrs.get("source_split") or "test"))
        table = lf.objects
        objects = ObjectInfo.from_table(table)
        idx = range(lf.num_frames) if frames is None else frames
        it = idx
        if progress:
            from tqdm import tqdm
            it = tqdm(idx, desc="eval", unit="frame")
        for i in it:
            frame = lf.frame(i)
            t0 = time.perf_counter()
            preds = predictor(frame)
            timings = dict(preds.timings)
            res = dict(zip(("noicp", "icp"), estimate(preds, objects, cfg, timings, frame.features[:, :3], poser,
                                                      frame.features)))
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
        num_frames = len(idx)
    return _finish(gt_rows, counts, times, table, cfg, keys, icp, str(label_path), num_frames, bop_rows, out_dir,
                   device, icp_status if icp else None, csv_name)


def _finish(gt_rows, counts, times, table, cfg, keys, icp, label_file, num_frames, bop_rows, out_dir, device,
            icp_status=None, csv_name="argen_argen-test.csv") -> dict:
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
    summary = {"label_file": label_file, "num_frames": num_frames, "icp": icp, "config": asdict(cfg),
               "objects": objs, "mean": mean, "f1": f1, "timing_ms": timing_ms,
               "fps": 1000.0 / timing_ms["total"] if timing_ms["total"] > 0 else float("inf"),
               "device": device, "bop_csv": csv_name, "icp_refinement": icp_status, "instances": gt_rows,
               "curve": {name: {"k": ks.tolist(), "accuracy": acc.tolist()} for name, (ks, acc) in curves.items()}}
    write_report(Path(out_dir), summary, curves, bop_rows)
    return summary
