"""Where a two-stage model loses the instances that `detector eval --icp` counted as missed (no pose within
``--threshold`` of the diameter, ADD(-S) after ICP): for each, whether stage 1 voted a centre of its object near it,
only a centre of another object, or one of its own whose stage-2 pose was then wrong, or right but scored under
``min_score``; of the wrong poses, whether ICP from any of its starts (the stage-2 pose, its other verified
hypotheses, its half turns) would have reached a right one, which tells ICP's choice among its results from stage 2's
poses, and whether ICP from the true pose on its points stays right, which tells a failure of the starts from one
of the points (a detection with too few points for ICP counts as neither). It reruns the model on the missed
instances' frames with the report's settings (give eval's ``--seed`` and ``--set``) and reads the poses before the
score threshold. Usage:

    python bench/probe_misses.py MODEL LABELS REPORT [--seed S] [--set KEY=V ...] [--min-visib V] [--json OUT]

REPORT: the report.json that `detector eval MODEL LABELS --icp` wrote. Prints a table per object and the frames.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter, defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from argen.errors import ArgenError
from argen.h5 import LabelFile
from detector.checkpoint import load_checkpoint
from detector.errors import DetectorError
from detector.evaluation.metrics import pose_error
from detector.geometry.icp import icp_from_start, icp_points, icp_starts
from detector.geometry.types import Detection, GeometryConfig, ObjectInfo
from detector.geometry.voting import detect
from detector.infer import (checkpoint_geometry_config, checkpoint_objects, checkpoint_poser, estimate,
                            missing_surfaces, split_sets)
from detector.net_dtype import resolve_net_dtype
from detector.stage1.predictor import network_predictor

#: The causes, in the order a miss is tested for them.
CAUSES = ("no stage-1 centre", "another object's centre only", "no stage-2 pose", "wrong pose",
          "right pose, score under min_score", "right pose, not chosen")
#: Of the wrong poses, those that ICP from another of its starts would have made right (a column after them).
START_RIGHT = "of them, an ICP start right"
#: Of the wrong poses, those whose points hold the true pose: ICP from the true pose on them stays right, so what
#: failed is the start (stage 2's poses), not the points (a column after them).
TRUTH_HOLDS = "of them, ICP from the truth stays right"
#: The table's columns.
COLUMNS = CAUSES[:4] + (START_RIGHT, TRUTH_HOLDS) + CAUSES[4:]


def miss_cause(obj_id: int, centre: np.ndarray, diameter: float, stage1: list[Detection], posed: list[Detection],
               error, min_score: float, threshold: float = 0.1, near: float = 0.5) -> str:
    """Why a missed instance of ``obj_id`` was missed, one of :data:`CAUSES`.

    centre: (3,) metres, its true box centre; diameter: metres; stage1: the frame's stage-1 detections; posed: its
    final detections (after stage 2 and ICP) before any score threshold; error: a function of a detection giving its
    pose error in metres (ADD(-S) against this instance); a detection is near when its box centre lies within
    ``near`` x the diameter of ``centre``; a pose is right under ``threshold`` x the diameter.
    """
    def close(dets: list[Detection]) -> list[Detection]:
        return [d for d in dets if np.linalg.norm(d.control_points[8] - centre) < near * diameter]

    mine = [d for d in close(stage1) if d.obj_id == obj_id]
    if not mine:
        return CAUSES[1] if close(stage1) else CAUSES[0]
    poses = [d for d in close(posed) if d.obj_id == obj_id]
    if not poses:
        return CAUSES[2]
    best = max(poses, key=lambda d: d.score)
    if error(best) >= threshold * diameter:
        return CAUSES[3]
    return CAUSES[4] if best.score < min_score else CAUSES[5]


def icp_errors_from(detection: Detection, cloud: np.ndarray, objects: ObjectInfo, cfg: GeometryConfig,
                    starts: list, error) -> list[float]:
    """The pose error (metres, ``error`` of a detection) of ICP's result from each start [(R (3,3), t (3,) metres),
    ...] on the points ICP takes of an unrefined two-stage detection's own points (``detection.points``, rows of
    ``cloud`` (M,3) camera metres), as :func:`detector.geometry.icp.refine` runs each start. Empty when the
    detection has too few points for ICP."""
    if detection.points is None or len(detection.points) < cfg.icp_min_points:
        return []
    pts = icp_points(np.asarray(cloud)[detection.points], cfg)
    out = []
    for R0, t0 in starts:
        R, t = icp_from_start(pts, detection.obj_id, np.asarray(R0, np.float64), np.asarray(t0, np.float64),
                              objects, cfg)
        out.append(float(error(replace(detection, R=R, t=t))))
    return out


def icp_start_errors(detection: Detection, cloud: np.ndarray, objects: ObjectInfo, cfg: GeometryConfig, error
                     ) -> list[float]:
    """:func:`icp_errors_from` the detection's own starts (:func:`detector.geometry.icp.icp_starts`: its pose, its
    other verified hypotheses, its half turns), before :func:`detector.geometry.icp.refine` chooses among the results
    by their fit. Empty when the detection has too few points for ICP."""
    starts = icp_starts(detection.obj_id, detection.R, detection.t, objects, cfg, detection.alternatives)
    return icp_errors_from(detection, cloud, objects, cfg, starts, error)


def icp_from_truth_error(detection: Detection, cloud: np.ndarray, objects: ObjectInfo, cfg: GeometryConfig,
                         R_true: np.ndarray, t_true: np.ndarray, error) -> float | None:
    """:func:`icp_errors_from` the true pose (R_true (3,3), t_true (3,) metres) alone: small when the detection's
    points hold the true pose (it failed at its starts), large when they pull away from it (its points are wrong).
    None when the detection has too few points for ICP."""
    errors = icp_errors_from(detection, cloud, objects, cfg, [(R_true, t_true)], error)
    return errors[0] if errors else None


def missed_instances(report: dict, threshold: float) -> dict[int, list[tuple[int, int]]]:
    """{frame: [(obj_id, k), ...]}: the report's instances without a pose within ``threshold`` of the diameter after
    ICP (a row's "icp" is its matched pose's ADD(-S) error in metres, None when unmatched; "diameter" in metres);
    k: which of the frame's evaluated instances of that object it is (the report lists them in the label file's
    order)."""
    out: dict[int, list[tuple[int, int]]] = defaultdict(list)
    seen: Counter = Counter()
    for row in report["instances"]:
        key = (row["frame"], row["obj_id"])
        if "icp" not in row:
            raise DetectorError("the report holds no poses after ICP: run detector eval with --icp")
        if row["icp"] is None or row["icp"] >= threshold * row["diameter"]:
            out[row["frame"]].append((row["obj_id"], seen[key]))
        seen[key] += 1
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("labels")
    ap.add_argument("report")
    ap.add_argument("--seed", type=int, default=0, help="the sampling seed detector eval used")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="as detector eval --set")
    ap.add_argument("--min-visib", type=float, default=0.1, help="as detector eval --min-visib")
    ap.add_argument("--threshold", type=float, default=0.1, help="ADD(-S) share of the diameter")
    ap.add_argument("--json", type=Path, help="write the causes per instance here")
    a = ap.parse_args()
    try:
        report = json.loads(Path(a.report).read_text())
        missed = missed_instances(report, a.threshold)
        geometry, sampling, infer_sets = split_sets(a.sets)
        ck = load_checkpoint(a.model, "cpu", sampling=sampling or None)
        if ck.stage2_net is None:
            raise DetectorError(f"{a.model} is not a two-stage model")
        cfg = checkpoint_geometry_config(ck, None, True, None, geometry)
        loose = checkpoint_geometry_config(ck, None, True, None, geometry + ["geometry.min_score=0.0",
                                                                          "geometry.min_score_unrefined=0.0"])
        LabelFile(a.labels).close()
        objects, _ = checkpoint_objects(ck)
        if (warning := missing_surfaces(cfg, objects, a.model)) is not None:
            print(f"warning: {warning}", file=sys.stderr)
        # the networks' number format the report was made with (float32 before reports recorded it)
        net_dtype = resolve_net_dtype((report.get("run") or {}).get("net_dtype") or "float32")
        poser = checkpoint_poser(ck, objects, "cpu", a.seed, infer_sets, net_dtype)
    except (OSError, ValueError, KeyError, ArgenError, DetectorError) as exc:
        sys.exit(f"probe_misses: {exc}")
    torch.set_num_threads(2)
    pred = network_predictor(ck, a.seed, net_dtype=net_dtype)
    rows, per = [], defaultdict(Counter)
    with LabelFile(a.labels) as lf:
        table = lf.objects
        for i in sorted(missed):
            fr = lf.frame(i)
            p = pred(fr)
            stage1 = detect(p.xyz, p.obj_ids, p.confidence, p.control_points, objects, cfg, {})
            unrefined, posed = estimate(p, objects, loose, {}, fr.features[:, :3], poser, fr.features)
            inst = fr.instances
            for oid, k in missed[i]:
                ours = np.flatnonzero((inst.obj_id == oid) & (np.asarray(inst.visib_fract) >= a.min_visib))
                if k >= len(ours):
                    sys.exit(f"probe_misses: frame {i} has fewer instances of object {oid} than the report "
                             "(another label file, or another --min-visib?)")
                g, m = int(ours[k]), table.index(oid)
                dia = float(table.diameters[m])
                err = lambda d, g=g, m=m: pose_error(table.model_points[m], bool(table.symmetric[m]),  # noqa: E731
                                                     inst.R[g], inst.t[g], d.R, d.t)
                cause = miss_cause(oid, inst.control_points[g][8], dia, stage1, posed, err, cfg.min_score,
                                   a.threshold)
                per[oid][cause] += 1
                row = {"frame": i, "obj_id": oid, "visib_fract": round(float(inst.visib_fract[g]), 3), "cause": cause}
                if cause == "wrong pose":  # the best-scoring unrefined pose near it (after the colour and part
                    # checks, which turn some objects' unrefined poses once ICP has started from them as they were)
                    near = [d for d in unrefined if d.obj_id == oid and
                            np.linalg.norm(d.control_points[8] - inst.control_points[g][8]) < 0.5 * dia]
                    best = max(near, key=lambda d: d.score) if near else None
                    errors = icp_start_errors(best, fr.features[:, :3], objects, cfg, err) if near else []
                    row["icp_start_right"] = bool(errors) and min(errors) < a.threshold * dia
                    per[oid][START_RIGHT] += row["icp_start_right"]
                    held = icp_from_truth_error(best, fr.features[:, :3], objects, cfg, inst.R[g], inst.t[g],
                                                err) if near else None
                    row["icp_from_truth_right"] = held is not None and held < a.threshold * dia
                    per[oid][TRUTH_HOLDS] += row["icp_from_truth_right"]
                rows.append(row)
    names = {int(o["obj_id"]): o["name"] for o in report.get("objects", [])}
    print(f"{len(rows)} missed instances of {len(report['instances'])} ({a.report}), by where they were lost:")
    print("| object | missed | " + " | ".join(COLUMNS) + " |")
    print("|---|---:|" + "---:|" * len(COLUMNS))
    for oid in sorted(per):
        print(f"| {names.get(oid, oid)} | {sum(per[oid][c] for c in CAUSES)} | "
              + " | ".join(str(per[oid][c]) for c in COLUMNS) + " |")
    total = Counter()
    for c in per.values():
        total.update(c)
    print(f"| all | {len(rows)} | " + " | ".join(str(total[c]) for c in COLUMNS) + " |")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
