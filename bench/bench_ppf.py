"""Baseline: OpenCV's point-pair-feature detector (Drost et al. 2010, ``cv2.ppf_match_3d``) on a BOP test set:
ADD(-S) accuracy at 10 % of the diameter without and with OpenCV's ICP, and wall-clock time a frame.

    .venv/bin/python bench/bench_ppf.py [--dataset ../shared/data/ycbv_real] [--split test] [--scene 0]
        [--objects 8 14 21] [--frames N] [--sampling-step 0.07] [--scene-ref-step 0.025] [--scene-step 0.05]
        [--scene-step-of model|scene] [--no-icp] [--threads 1] [--ours REPORT.json] [--out DIR]

It needs the meshes and no training data. One ``PPF3DDetector`` is trained per object on ``--model-points``
surface samples of its mesh with face normals. Each frame's scene is the whole depth image, as our detector sees
it: every pixel with depth in (0, ``--max-depth``] (default: the project's working volume for the dataset,
``argen.label.default_max_depth``; 2 m for a BOP dataset of a real sensor), back-projected with normals from the
depth grid (``argen.features.frame_points``). No ground truth or mask crops the scene. ``match()`` runs once per
object and frame; its best poses by vote count (as many as the object's instances in the frame, BOP's
``test_targets_bop19.json`` ``inst_count``) are the estimates, score = votes. ``--no-icp`` skips the refinement
by ``cv2.ppf_match_3d_ICP`` (OpenCV sample's 100 iterations, its other defaults) of those poses.

Scoring is the project's: ADD, or ADD-S for objects with symmetries in models_info.json
(``ObjectModel.symmetric``), on the label files' 1000 seeded model points (``argen.label.object_table``),
detections matched to ground truth greedily by score (``detector.evaluation.metrics.match_frame``), instances under 10 %
visible ignored. Times: median over frames of wall-clock seconds; a frame's time is its scene cloud plus
``match()`` of every object (plus ICP of every pose), one process, ``cv2.setNumThreads(--threads)``. The
``match()`` of the pip OpenCV build is single-threaded whatever the setting (its parallel loop is OpenMP,
which that build does not use).

Settings (see ``--help``) and why:
  * relativeSamplingStep 0.07, numAngles 30 (OpenCV's default and Drost's): OpenCV's default step 0.05 keeps
    1700-2100 model points of the three YCB-Video objects, and training the foam brick took 31 minutes on a
    2-core machine (its hash table walks a chain for every repeated feature, and flat faces repeat features;
    0.025, the sample's, keeps 6100-8100). 0.07 keeps about as many points (930-1110; 8-52 s of training) as
    Drost's sampling distance 0.05 x diameter would (710-1320). The step also sets the distance bins (step x
    the model's box diagonal) and the pose-clustering radius (step, in cloud units).
  * Clouds in millimetres, as in the OpenCV sample's data: the clustering radius is absolute (0.07 mm then, so
    poses are hardly merged; in metres it would merge all poses within 7 cm whatever their rotation).
  * relativeSceneSampleStep 1/40 (the OpenCV sample's): every 40th sampled scene point is a reference point.
  * Scene sampling distance 0.05 x the object's diameter (Drost: scene and model sampled alike). OpenCV takes
    it relative to the scene's bounding box (not the model diameter, as its documentation says), so it is
    passed as 0.05 x diameter / the cloud's longest box side (``--scene-step-of model``);
    ``--scene-step-of scene`` passes ``--scene-step`` unchanged, as the OpenCV sample does on its cropped scene.

Measured here (2-core shared CPU, 1 thread, ycbv_real, 10 frames, 30 instances), ADD(-S)@10 % without / with
ICP: gelatin box 0 / 10 %, mug 0 / 0 %, foam brick (ADD-S) 60 / 60 %, all 20.0 / 23.3 %; 65 s a frame (match
19 + 7 + 39 s for the three objects, ICP 1.2 s). On the first 3 frames (main 11.1 / 22.2 %): step 0.1, 22.2 /
22.2 % at 12 s a frame; the scene step taken as OpenCV's (0.05 of the scene box, 5-cm cells) 0 / 0 % at 0.3 s.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from argen import bop
from argen.errors import ArgenError
from argen.features import frame_points
from argen.label import default_max_depth, load_label_objects, object_table
from detector.errors import DetectorError
from detector.evaluate import bop19_summary
from detector.evaluation.metrics import accuracy, match_frame, pose_error
from detector.report import bop_csv_name, bop_row, default_dataset_name, json_safe, write_bop_csv

PPF_UNIT = 1000.0  # PPF clouds are in millimetres (see the module docstring): metres x PPF_UNIT
MAX_SCENE_CELLS = 256  # cap on OpenCV's scene grid cells a side: it allocates (n+1)^3 cell lists (~400 MB at 256)
K_ADD = 0.10


@dataclass(frozen=True)
class PPFSettings:
    """The detector's settings. sampling_step: relativeSamplingStep (model grid 1/step cells a side of its box,
    distance bins step x box diagonal); distance_step: relativeDistanceStep (stored by OpenCV, not used by its
    matching); num_angles: numAngles; scene_ref_step: relativeSceneSampleStep; scene_step: scene sampling distance,
    a fraction of the model diameter (scene_step_of "model") or of the scene's bounding box ("scene", OpenCV's
    own meaning); model_points: surface samples the model is trained on; icp_iterations: ICP iterations."""

    sampling_step: float = 0.07
    distance_step: float = 0.05
    num_angles: int = 30
    scene_ref_step: float = 1 / 40
    scene_step: float = 0.05
    scene_step_of: str = "model"
    model_points: int = 20000
    icp_iterations: int = 100


def ppf_cloud(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """An OpenCV PPF cloud: points (N,3) metres and unit normals (N,3) -> (N,6) float32, millimetres + normals."""
    return np.hstack([np.asarray(points, np.float64) * PPF_UNIT, np.asarray(normals, np.float64)]).astype(np.float32)


def model_surface(mesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform surface samples of a mesh (metres) with its face normals: points (n,3) metres, normals (n,3)."""
    # lazy: trimesh loads slowly and only model sampling needs it here
    import trimesh

    pts, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts, np.float64), np.asarray(mesh.face_normals[face], np.float64)


def train_detector(model_pc: np.ndarray, s: PPFSettings):
    """A trained ``cv2.ppf_match_3d_PPF3DDetector`` for a model cloud (N,6) mm (:func:`ppf_cloud`)."""
    det = cv2.ppf_match_3d_PPF3DDetector(s.sampling_step, s.distance_step, s.num_angles)
    det.trainModel(model_pc)
    return det


def scene_distance(scene_pc: np.ndarray, diameter: float, s: PPFSettings) -> float:
    """relativeSceneDistance for ``match()``: scene sampling distance ``s.scene_step`` x diameter (metres) over the
    longest side of the scene cloud's (N,6, mm) box, or ``s.scene_step`` itself for scene_step_of "scene"; at
    least 1 / MAX_SCENE_CELLS."""
    if s.scene_step_of == "scene":
        return float(s.scene_step)
    extent = float(np.ptp(scene_pc[:, :3], axis=0).max()) / PPF_UNIT
    return float(np.clip(s.scene_step * diameter / max(extent, 1e-9), 1.0 / MAX_SCENE_CELLS, 1.0))


def match_object(det, scene_pc: np.ndarray, diameter: float, count: int, s: PPFSettings) -> list:
    """The ``count`` best-voted poses (``cv2.ppf_match_3d_Pose3D``, pose in mm) of one object in a scene (N,6) mm."""
    res = det.match(scene_pc, s.scene_ref_step, scene_distance(scene_pc, diameter, s))
    return sorted(res, key=lambda p: -p.numVotes)[:count]


def pose_rt(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A PPF pose (4,4), translation mm -> R (3,3), t (3,) metres (model -> camera)."""
    pose = np.asarray(pose, np.float64)
    return pose[:3, :3].copy(), pose[:3, 3] / PPF_UNIT


def refine(icp, model_pc: np.ndarray, scene_pc: np.ndarray, poses: list) -> list[tuple[np.ndarray, np.ndarray]]:
    """OpenCV ICP of each pose of ``poses`` (Pose3D) on the scene: [(R (3,3), t (3,) metres)]. The model cloud
    (N,6) mm moves onto the scene cloud (M,6) mm."""
    out = []
    for p in poses:
        start = np.asarray(p.pose, np.float64)
        moved = cv2.ppf_match_3d.transformPCPose(model_pc, start)
        _, _, delta = icp.registerModelToScene(moved, scene_pc)
        out.append(pose_rt(np.asarray(delta, np.float64) @ start))
    return out


def scene_cloud(depth: np.ndarray, K: np.ndarray, max_depth: float) -> np.ndarray:
    """The whole frame as a PPF cloud (N,6) mm: every pixel of depth (H,W) metres in (0, max_depth] metres,
    back-projected with K (3,3), normals from the depth grid (toward the camera)."""
    fp = frame_points(depth, K, None, depth.size, 0.0, np.random.default_rng(0), max_depth)
    return ppf_cloud(fp.features[:, :3], fp.features[:, 6:9])


@dataclass
class ObjectRun:
    """One object's trained detector and scoring data: model_pc (N,6) mm; points (P,3) metres (metric points);
    diameter metres; symmetric: ADD-S instead of ADD; train_s: training seconds."""

    obj_id: int
    name: str
    det: object
    model_pc: np.ndarray
    points: np.ndarray
    diameter: float
    symmetric: bool
    train_s: float


def prepare_objects(models_dir: Path, ids: list[int], s: PPFSettings, seed: int) -> list[ObjectRun]:
    """Load and train every object of ``ids`` (timed one by one)."""
    objects = load_label_objects(models_dir, ids)
    table = object_table(list(objects.values()))
    runs = []
    for oid in ids:
        o, m = objects[oid], table.index(oid)
        model_pc = ppf_cloud(*model_surface(o.mesh, s.model_points, seed))
        t0 = time.perf_counter()
        det = train_detector(model_pc, s)
        runs.append(ObjectRun(oid, o.name, det, model_pc, table.model_points[m].astype(np.float64),
                              float(table.diameters[m]), bool(table.symmetric[m]), time.perf_counter() - t0))
        print(f"trained object {oid} ({o.name}) in {runs[-1].train_s:.1f} s", file=sys.stderr, flush=True)
    return runs


def frame_targets(root: Path, split: str, scene: bop.BopScene, im_id: int) -> dict[int, int]:
    """{obj_id: instances to find} of a frame: BOP's test targets when the dataset has the file, else its
    ground-truth instances at least 10 % visible (the same rule)."""
    path = root / bop.TEST_TARGETS
    targets = bop.load_test_targets(path) if path.is_file() else bop.test_targets(root, split)
    return {t["obj_id"]: t["inst_count"] for t in targets
            if t["scene_id"] == scene.scene_id and t["im_id"] == im_id}


def score(run: ObjectRun, gts: list[bop.FrameGT], valid: np.ndarray, votes: list[float],
          poses: list[tuple[np.ndarray, np.ndarray]], symmetric: bool) -> np.ndarray:
    """(G,) pose error (metres; inf = missed) of each of the object's G ground-truth instances ``gts``, with
    detections ``poses`` [(R, t metres)] matched greedily by ``votes``; valid: (G,) bool instances that count;
    symmetric: ADD-S, else ADD."""
    err = np.array([[pose_error(run.points, symmetric, g.R, g.t, R, t) for g in gts] for R, t in poses],
                   np.float64).reshape(len(poses), len(gts))
    return match_frame(np.asarray(votes, np.float64), err, np.full(len(gts), run.diameter), valid).gt_error


def run_frames(root: Path, split: str, scene: bop.BopScene, im_ids: list[int], runs: list[ObjectRun],
               s: PPFSettings, max_depth: float, icp_on: bool) -> tuple[list[dict], list[dict], dict]:
    """Match every object in every frame: (per-instance rows, per-object-and-frame rows, BOP rows per variant)."""
    icp = cv2.ppf_match_3d_ICP(s.icp_iterations) if icp_on else None
    keys = ("noicp", "icp") if icp_on else ("noicp",)
    inst_rows, obj_rows, bop_rows = [], [], {k: [] for k in keys}
    for im_id in im_ids:
        t0 = time.perf_counter()
        pc = scene_cloud(scene.read_depth(im_id), scene.cameras[im_id].K, max_depth)
        cloud_s = time.perf_counter() - t0
        targets = frame_targets(root, split, scene, im_id)
        frame_obj, frame_s = [], {"noicp": cloud_s, "icp": cloud_s}
        for run in runs:
            if not targets.get(run.obj_id):
                continue  # not a target in this frame (BOP tells the method which objects to find)
            t0 = time.perf_counter()
            found = match_object(run.det, pc, run.diameter, targets[run.obj_id], s)
            match_s = time.perf_counter() - t0
            est = {"noicp": [pose_rt(p.pose) for p in found]}
            icp_s = 0.0
            if icp_on:
                t0 = time.perf_counter()
                est["icp"] = refine(icp, run.model_pc, pc, found)
                icp_s = time.perf_counter() - t0
            frame_s["noicp"] += match_s
            frame_s["icp"] += match_s + icp_s
            frame_obj.append((run, found, est))
            obj_rows.append({"im_id": im_id, "obj_id": run.obj_id, "match_s": match_s, "icp_s": icp_s,
                             "points": len(pc), "votes": [int(p.numVotes) for p in found]})
        for run, found, est in frame_obj:
            votes = [float(p.numVotes) for p in found]
            sel = [g for g in scene.gts[im_id] if g.obj_id == run.obj_id]
            idx = [i for i, g in enumerate(scene.gts[im_id]) if g.obj_id == run.obj_id]
            infos = scene.gt_infos.get(im_id, [])
            valid = np.array([float(infos[i].get("visib_fract", 1.0)) >= 0.1 if infos else True for i in idx], bool)
            errs = {k: score(run, sel, valid, votes, est[k], run.symmetric) for k in keys}
            errs |= {f"{k}_adds": score(run, sel, valid, votes, est[k], True) for k in keys}
            inst_rows += [{"im_id": im_id, "obj_id": run.obj_id, "diameter": run.diameter,
                           **{k: float(e[j]) for k, e in errs.items()}} for j in np.flatnonzero(valid)]
            for k in keys:
                bop_rows[k] += [bop_row(scene.scene_id, im_id, run.obj_id, v, R, t, frame_s[k])
                                for v, (R, t) in zip(votes, est[k])]
        print(f"frame {im_id}: {len(pc)} points, {frame_s['noicp'] * 1000:.0f} ms"
              + (f" ({frame_s['icp'] * 1000:.0f} ms with ICP)" if icp_on else ""), file=sys.stderr, flush=True)
        obj_rows.append({"im_id": im_id, "obj_id": None, "cloud_s": cloud_s, "frame_s": frame_s})
    return inst_rows, obj_rows, bop_rows


def summarise(runs: list[ObjectRun], inst_rows: list[dict], obj_rows: list[dict], keys: tuple) -> dict:
    """Per-object ADD(-S)@10 % (without / with ICP), median ms per frame, and the same over all objects."""
    def acc(rows, k):
        return accuracy(np.array([r[k] for r in rows]), np.array([r["diameter"] for r in rows]), K_ADD)

    def med_ms(vals):
        return 1000 * statistics.median(vals) if vals else float("nan")

    objs = []
    for run in runs:
        rows = [r for r in inst_rows if r["obj_id"] == run.obj_id]
        per = [r for r in obj_rows if r["obj_id"] == run.obj_id]
        objs.append({"obj_id": run.obj_id, "name": run.name, "symmetric": run.symmetric, "diameter": run.diameter,
                     "instances": len(rows), "train_s": run.train_s,
                     "add_10": {k: acc(rows, k) for k in keys},
                     "adds_10": {k: acc(rows, f"{k}_adds") for k in keys},
                     "match_ms": med_ms([r["match_s"] for r in per]), "icp_ms": med_ms([r["icp_s"] for r in per])})
    frames = [r for r in obj_rows if r["obj_id"] is None]
    return {"objects": objs, "all": {"instances": len(inst_rows), "add_10": {k: acc(inst_rows, k) for k in keys},
                                     "adds_10": {k: acc(inst_rows, f"{k}_adds") for k in keys},
                                     "mean_of_objects": {k: float(np.mean([o["add_10"][k] for o in objs]))
                                                         for k in keys}},
            "frame_ms": {k: med_ms([r["frame_s"][k] for r in frames]) for k in keys},
            "cloud_ms": med_ms([r["cloud_s"] for r in frames])}


def _pct(v) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{100 * v:.1f}"


def _ar(v) -> str:
    return "–" if v is None else f"{v:.3f}"


def read_ours(path: Path) -> dict:
    """A ``detector eval`` report.json: {"objects": {obj_id: (ADD@10 % w/o, with ICP)}, "frame_ms": total ms}."""
    try:
        rep = json.loads(Path(path).read_text())
        objs = {int(o["obj_id"]): (o["add"]["noicp"]["0.10"], (o["add"].get("icp") or {}).get("0.10"))
                for o in rep["objects"]}
        return {"objects": objs, "frame_ms": float(rep["timing_ms"]["total"])}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ArgenError(f"--ours {path}: not a readable detector eval report.json ({exc.__class__.__name__})") \
            from None


def table(summary: dict, keys: tuple, ours: dict | None) -> str:
    """The per-object Markdown table (and ours beside it when given)."""
    last = keys[-1]
    bop19 = summary.get("bop19", {}).get(last, {})
    ar_of = {int(k): v["ar"] for k, v in bop19.get("objects", {}).items()}
    head = ("| object | inst. | PPF w/o ICP | PPF + ICP | ADD-S for all, "
            f"{'+ ICP' if last == 'icp' else 'w/o ICP'} | BOP19 AR, {'+ ICP' if last == 'icp' else 'w/o ICP'} | "
            "match ms/frame | ICP ms/frame | train s |")
    rule = "|---|---:|---:|---:|---:|---:|---:|---:|---:|"
    if ours:
        head += " ours w/o ICP | ours + ICP |"
        rule += "---:|---:|"
    lines = [head, rule]
    for o in summary["objects"]:
        row = (f"| {o['obj_id']} {o['name']}{'*' if o['symmetric'] else ''} | {o['instances']} | "
               f"{_pct(o['add_10']['noicp'])} | {_pct(o['add_10'].get('icp'))} | {_pct(o['adds_10'][last])} | "
               f"{_ar(ar_of.get(o['obj_id']))} | {o['match_ms']:.0f} | {o['icp_ms']:.0f} | {o['train_s']:.1f} |")
        if ours:
            a, b = ours["objects"].get(o["obj_id"], (None, None))
            row += f" {_pct(a)} | {_pct(b)} |"
        lines.append(row)
    a, fm = summary["all"], summary["frame_ms"]
    icp_ms = fm["icp"] - fm["noicp"] if "icp" in fm else 0.0
    row = (f"| **all** | {a['instances']} | {_pct(a['add_10']['noicp'])} | {_pct(a['add_10'].get('icp'))} | "
           f"{_pct(a['adds_10'][last])} | {_ar(bop19.get('bop19_average_recall'))} | {fm['noicp']:.0f} a frame | {icp_ms:.0f} a frame | |")
    if ours:
        row += f" {ours['frame_ms']:.0f} ms a frame | |"
    lines.append(row)
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    d = PPFSettings()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, default=Path("../shared/data/ycbv_real"))
    ap.add_argument("--split", default="test")
    ap.add_argument("--scene", type=int, default=None, help="scene id (default: the split's first)")
    ap.add_argument("--objects", type=int, nargs="+", default=None, help="object ids (default: all in the scene)")
    ap.add_argument("--frames", type=int, default=None, help="only the first N frames")
    ap.add_argument("--models", type=Path, default=None, help="models folder (default: DATASET/models)")
    ap.add_argument("--max-depth", type=float, default=None, help="metres (default: the dataset's working volume)")
    ap.add_argument("--sampling-step", type=float, default=d.sampling_step, help="relativeSamplingStep")
    ap.add_argument("--distance-step", type=float, default=d.distance_step, help="relativeDistanceStep")
    ap.add_argument("--num-angles", type=int, default=d.num_angles, help="numAngles")
    ap.add_argument("--scene-ref-step", type=float, default=d.scene_ref_step, help="relativeSceneSampleStep")
    ap.add_argument("--scene-step", type=float, default=d.scene_step,
                    help="scene sampling distance (see --scene-step-of)")
    ap.add_argument("--scene-step-of", choices=("model", "scene"), default=d.scene_step_of,
                    help="model: --scene-step x object diameter; scene: relativeSceneDistance as given (OpenCV's)")
    ap.add_argument("--model-points", type=int, default=d.model_points)
    ap.add_argument("--icp-iterations", type=int, default=d.icp_iterations)
    ap.add_argument("--no-icp", action="store_true", help="skip the ICP refinement")
    ap.add_argument("--threads", type=int, default=1, help="cv2.setNumThreads")
    ap.add_argument("--seed", type=int, default=0, help="model surface sampling seed")
    ap.add_argument("--ours", type=Path, default=None, help="a detector eval report.json to print beside PPF")
    ap.add_argument("--out", type=Path, default=None, help="folder for bench_ppf.json and the BOP results CSVs")
    return ap.parse_args(argv)


def check_args(args: argparse.Namespace) -> PPFSettings:
    """The settings from the arguments; ArgenError on values OpenCV would reject or crash on."""
    if not args.dataset.is_dir():
        raise ArgenError(f"dataset folder not found: {args.dataset}")
    if not 0 < args.sampling_step <= 1 or not 0 < args.scene_step <= 1 or not 0 < args.scene_ref_step <= 1:
        raise ArgenError("--sampling-step, --scene-step and --scene-ref-step must be in (0, 1]")
    if args.num_angles < 1 or args.model_points < 100 or args.icp_iterations < 1:
        raise ArgenError("--num-angles and --icp-iterations must be >= 1, --model-points >= 100")
    if args.frames is not None and args.frames < 1:
        raise ArgenError("--frames must be >= 1")
    return PPFSettings(args.sampling_step, args.distance_step, args.num_angles, args.scene_ref_step,
                       args.scene_step, args.scene_step_of, args.model_points, args.icp_iterations)


def run(args: argparse.Namespace) -> dict:
    """The whole benchmark; returns the summary (also written to ``--out``)."""
    s = check_args(args)
    cv2.setNumThreads(args.threads)
    root = args.dataset
    scene_id = args.scene if args.scene is not None else bop.list_scenes(root, args.split)[0]
    scene = bop.load_scene(root, args.split, scene_id)
    im_ids = scene.im_ids[: args.frames] if args.frames else scene.im_ids
    if not im_ids:
        raise ArgenError(f"scene {scene_id} of {root / args.split} has no frames with ground truth")
    in_scene = sorted({g.obj_id for i in im_ids for g in scene.gts[i]})
    ids = args.objects or in_scene
    models_dir = args.models or root / "models"
    max_depth = args.max_depth if args.max_depth is not None else default_max_depth(root)
    ours = read_ours(args.ours) if args.ours else None
    print("$", shlex.join([sys.executable, *sys.argv]), flush=True)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, cv2 {cv2.__version__}, "
          f"cv2 threads {cv2.getNumThreads()}; dataset {root} {args.split}/{scene_id:06d}, {len(im_ids)} frames, "
          f"objects {ids}, depth (0, {max_depth:g}] m", flush=True)
    print("settings:", json.dumps(asdict(s)), flush=True)
    runs = prepare_objects(models_dir, ids, s, args.seed)
    keys = ("noicp",) if args.no_icp else ("noicp", "icp")
    inst_rows, obj_rows, bop_rows = run_frames(root, args.split, scene, im_ids, runs, s, max_depth, not args.no_icp)
    summary = summarise(runs, inst_rows, obj_rows, keys)
    argen_json = (root / "argen.json").read_text() if (root / "argen.json").is_file() else ""
    images = {(scene_id, i) for i in im_ids}
    summary["bop19"] = {k: bop19_summary(bop_rows[k], images, root, args.split, argen_json) for k in keys}
    print(table(summary, keys, ours), flush=True)
    for k in keys:
        b = summary["bop19"][k]
        print(f"BOP19 AR {'with' if k == 'icp' else 'without'} ICP: " + (
            f"{b['bop19_average_recall']:.3f} (VSD {b['bop19_average_recall_vsd']:.3f}, MSSD "
            f"{b['bop19_average_recall_mssd']:.3f}, MSPD {b['bop19_average_recall_mspd']:.3f})"
            if "skipped" not in b else f"not computed: {b['skipped']}"), flush=True)
    print(f"median ms a frame: {summary['frame_ms']['noicp']:.0f} without ICP"
          + (f", {summary['frame_ms']['icp']:.0f} with ICP" if "icp" in keys else "")
          + f" (scene cloud {summary['cloud_ms']:.0f}); ADD(-S)@10 %, * = symmetric (ADD-S)", flush=True)
    result = {"command": shlex.join([sys.executable, *sys.argv]), "dataset": str(root), "split": args.split,
              "scene_id": scene_id, "im_ids": im_ids, "max_depth_m": max_depth, "threads": cv2.getNumThreads(),
              "cores": os.cpu_count(), "opencv": cv2.__version__, "settings": asdict(s), **summary,
              "instances": inst_rows, "per_frame": obj_rows, "ours": ours}
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "bench_ppf.json").write_text(json.dumps(json_safe(result), indent=1, allow_nan=False) + "\n")
        dataset = default_dataset_name(str(root))
        for k, rows in bop_rows.items():
            write_bop_csv(args.out / bop_csv_name("ppf" if k == "noicp" else "ppficp", dataset, args.split), rows)
        print(f"wrote {args.out}/bench_ppf.json and the BOP results CSVs", flush=True)
    return result


def main(argv: list[str] | None = None) -> None:
    try:
        run(parse_args(argv))
    except (ArgenError, DetectorError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
