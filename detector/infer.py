"""Inference: a checkpoint (or the ground truth, as an oracle) -> per-point predictions -> poses.

A predictor maps one frame (anything with ``features`` (N,9); evaluation passes ``argen.h5.FrameLabels``) to
:class:`Predictions`: :func:`network_predictor` runs a checkpoint's network on CPU or GPU, :func:`oracle_predictor`
returns the frame's ground-truth labels (checks the pose stage alone). :func:`estimate` turns predictions into
detections with :mod:`detector.pose` (voting, Kabsch, ICP) and, for a two-stage model, :class:`CropPoser`:
stage 2, which for each (object, centre) runs the crop network (:mod:`detector.cropnet`) to label the crop's
points as the object's or not and regress their model coordinates; RANSAC over 3-point Kabsch hypotheses
(:func:`detector.pose.ransac_kabsch`) turns the foreground correspondences into a pose. Optionally the crop is cut
again around the new centre and the pose recomputed (``recentre``), which forgives a larger stage-1 centre error.
The ``checkpoint_*`` helpers read a checkpoint's objects, pose settings and stage 2. ``detector eval`` and
``detector predict`` both infer through this module.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from detector.crops import CropConfig, ball_rows, crop_input, sample_crop
from detector.data import inference_batch
from detector.errors import DetectorError
from detector.pose import (
    Detection,
    ObjectInfo,
    PoseConfig,
    detect,
    fit_residuals,
    fit_rms,
    nms,
    ransac_kabsch,
    refine,
    support_radius,
    surface_support,
)


@dataclass
class CropPoseConfig:
    """Pose-from-crop options. fg_threshold: foreground probability for a correspondence; inlier: RANSAC
    inlier distance as a fraction of the diameter; hypotheses: RANSAC hypotheses; min_fg: fewest foreground
    points for a pose; recentre: crop again around the latest pose's centre and redo it this many times;
    samples: from the second crop on, each crop feeds the network this many random subsets of its points
    (disjoint where the crop holds enough) and pools their correspondences: the network sees a crop at the
    density it was trained on, ``crop.num_points``, while the pose gets several times more points (1 = one
    subset, the first design);
    verify: refit this many of the best RANSAC hypotheses and keep the one whose model surface fits the crop's
    foreground points best (trimmed point-to-plane RMS over the best ``verify_trim`` share, as ICP's acceptance
    test); 1 keeps RANSAC's own choice; fit_points: RANSAC scores its hypotheses, and the verification measures
    fits, on at most this many of the foreground points (a random subset; with several ``samples`` the foreground
    is that many times larger, and so would their cost be); the refits use them all."""

    fg_threshold: float = 0.5
    inlier: float = 0.05
    hypotheses: int = 128
    min_fg: int = 8
    recentre: int = 1
    samples: int = 1
    verify: int = 16
    verify_trim: float = 0.7
    fit_points: int = 256


#: CropPoseConfig keys that model files may hold but that are gone: ``recentre_min_shift`` limited the third and
#: later crops, which no model cuts any more (checkpoints/lm8.pt stores 0.04 with ``recentre`` 1: no effect).
RETIRED_INFER_KEYS = ("recentre_min_shift",)


def crop_subsets(rows: np.ndarray, num_points: int, samples: int, rng: np.random.Generator) -> list[np.ndarray]:
    """``samples`` subsets of a crop's rows (k,), each of ``num_points`` rows (:func:`detector.crops.sample_crop`):
    disjoint while the crop has enough points, then drawn independently. One subset is ``sample_crop``'s."""
    if samples <= 1:
        return [sample_crop(rows, num_points, rng)]
    perm = rng.permutation(rows)
    return [np.sort(perm[s * num_points:(s + 1) * num_points]) if (s + 1) * num_points <= len(rows)
            else sample_crop(rows, num_points, rng) for s in range(samples)]


@torch.no_grad()
def crop_predictions(net, features: np.ndarray, centres: np.ndarray, classes: np.ndarray, diameters: np.ndarray,
                     crop_cfg: CropConfig, normalisation: dict, seed: int = 0, device="cpu", samples: int = 1):
    """Run the crop network on ``samples`` point subsets (:func:`crop_subsets`) of one crop per centre.

    features: (N,9) the frame's label features; centres: (D,3) metres; classes: (D,) class indices;
    diameters: (D,) metres. Returns a list of D (rows (m,) into features, fg probability (m,), model coordinates
    (m,3) metres), the subsets' predictions one after the other (m = samples x ``crop_cfg.num_points``), or None
    where the crop holds fewer than ``crop_cfg.min_points`` points.
    """
    xyz = np.asarray(features[:, :3], np.float64)
    rng = np.random.default_rng(seed)
    batch, keep, out = [], [], [None] * len(centres)
    for k, (c, dia) in enumerate(zip(centres, diameters)):
        rows = ball_rows(xyz, c, crop_cfg.radius * dia)
        if len(rows) < crop_cfg.min_points:
            continue
        for sub in crop_subsets(rows, crop_cfg.num_points, samples, rng):
            batch.append(crop_input(features, sub, c, crop_cfg.radius * dia, normalisation))
            keep.append((k, sub))
    if not batch:
        return out
    feats = torch.from_numpy(np.stack(batch)).to(device)
    cls = torch.as_tensor(np.asarray(classes)[[k for k, _ in keep]], dtype=torch.int64, device=device)
    res = net(feats, cls)
    prob = torch.sigmoid(res["fg_logit"]).cpu().numpy()
    coords = res["coords"].double().cpu().numpy()
    pooled: dict[int, list] = {}
    for j, (k, rows) in enumerate(keep):
        pooled.setdefault(k, []).append((rows, prob[j], coords[j] * diameters[k]))
    for k, parts in pooled.items():
        out[k] = tuple(np.concatenate(z) for z in zip(*parts))
    return out


def pose_from_crop(xyz: np.ndarray, prob: np.ndarray, model_xyz: np.ndarray, diameter: float, cfg: CropPoseConfig,
                   rng: np.random.Generator, surface=None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A pose from one crop's predictions: xyz (n,3) camera metres, prob (n,), model_xyz (n,3) model metres.

    surface: (cKDTree of model points, normals) for ``cfg.verify`` > 1 (:meth:`detector.pose.ObjectInfo.surface`).
    Returns R (3,3), t (3,), the foreground (probability >= ``cfg.fg_threshold``) indices of the crop and the other
    verified hypotheses [(R, t), ...] from the best fit to the worst (empty without verification), or None with
    fewer than ``cfg.min_fg`` foreground points.
    """
    fg = np.flatnonzero(prob >= cfg.fg_threshold)
    if len(fg) < max(cfg.min_fg, 3):
        return None
    keep = cfg.verify if surface is not None else 1
    cands = ransac_kabsch(model_xyz[fg], xyz[fg], prob[fg], cfg.inlier * diameter, rng, cfg.hypotheses, keep=keep,
                          score_points=cfg.fit_points)
    if keep > 1:
        tree, normals = surface
        test = fg if len(fg) <= cfg.fit_points else fg[np.sort(rng.choice(len(fg), cfg.fit_points, replace=False))]
        res = fit_residuals(xyz[test], tree, normals, np.stack([c[0] for c in cands]), np.stack([c[1] for c in cands]),
                            0.05 * diameter)  # (verify, n): all hypotheses in one query
        fits = [fit_rms(r, cfg.verify_trim) for r in res]
        order = np.argsort(fits, kind="stable")
        R, t, _ = cands[int(order[0])]
        others = [(cands[j][0], cands[j][1]) for j in order[1:]]
    else:
        R, t, _ = cands
        others = []
    return R, t, fg, others


class CropPoser:
    """Stage 2 at inference: replaces each stage-1 detection's pose by the crop network's.

    net: a CropNet (eval mode); class_ids: its object ids (class c is ``class_ids[c]``); objects: the pose
    stage's :class:`detector.pose.ObjectInfo`; crop_cfg / cfg: crop and pose options; normalisation: colour
    normalisation of the network input. Calling it with (detections, features (N,9), timings) returns the
    detections with stage-2 poses, scores, ``points`` = the crop's foreground rows of ``features`` (ICP uses
    them) and ``alternatives`` = the crop's other verified hypotheses, best fit first (ICP may start from them). A detection whose crop yields no pose is dropped. Adds "stage2" seconds. The score is the share of the
    foreground points that the model surface under the pose explains to within ``support_distance`` of the
    diameter, but at least ``support_floor`` metres (:func:`detector.pose.surface_support`): it tells wrong poses and false detections from right ones
    far better than vote or inlier shares (measured on a validation capture).
    """

    def __init__(self, net, class_ids: list[int], objects, crop_cfg: CropConfig, normalisation: dict,
                 cfg: CropPoseConfig | None = None, device="cpu", seed: int = 0, support_distance: float = 0.02,
                 support_floor: float = 0.0):
        self.net, self.class_ids, self.objects = net, list(class_ids), objects
        self.support_distance, self.support_floor = support_distance, support_floor
        self.crop_cfg, self.normalisation, self.cfg = crop_cfg, normalisation, cfg or CropPoseConfig()
        self.device, self.seed = device, seed

    def _run(self, features, centres, oids, samples: int = 1):
        classes = np.array([self.class_ids.index(o) for o in oids], np.int64)
        dia = np.array([self.objects.diameters[o] for o in oids], np.float64)
        return crop_predictions(self.net, features, np.asarray(centres), classes, dia, self.crop_cfg,
                                self.normalisation, self.seed, self.device, samples)

    def __call__(self, detections: list[Detection], features: np.ndarray, timings: dict | None = None
                 ) -> list[Detection]:
        t0 = time.perf_counter()
        dets = [d for d in detections if d.obj_id in self.class_ids]
        xyz = np.asarray(features[:, :3], np.float64)
        rng = np.random.default_rng(self.seed)
        centres = [d.control_points[8] for d in dets]
        results: list = [None] * len(dets)  # (R, t, foreground rows of features, other hypotheses) of each detection
        for it in range(1 + self.cfg.recentre):
            todo = [k for k in range(len(dets)) if it == 0 or results[k] is not None]
            if not todo:
                break
            preds = self._run(features, [centres[k] for k in todo], [dets[k].obj_id for k in todo],
                              1 if it == 0 else self.cfg.samples)
            for k, pred in zip(todo, preds):
                if pred is None:
                    continue
                rows, prob, mxyz = pred
                oid = dets[k].obj_id
                res = pose_from_crop(xyz[rows], prob, mxyz, self.objects.diameters[oid], self.cfg, rng,
                                     self.objects.surface(oid) if self.cfg.verify > 1 else None)
                if res is None:
                    continue
                R, t, fg, others = res
                results[k] = (R, t, np.unique(rows[fg]), others)
                centres[k] = R @ self.objects.control_points[oid][8] + t
        out = []
        for d, r in zip(dets, results):
            if r is None:
                continue
            R, t, fg, others = r
            tree, normals = self.objects.surface(d.obj_id)
            dist = support_radius(self.support_distance, self.support_floor, self.objects.diameters[d.obj_id])
            score = surface_support(xyz[fg], tree, normals, R, t, dist)
            cps = self.objects.control_points[d.obj_id] @ R.T + t
            out.append(replace(d, R=R, t=t, score=score, control_points=cps, points=fg,
                               alternatives=others))
        if timings is not None:
            timings["stage2"] = timings.get("stage2", 0.0) + time.perf_counter() - t0
        return out


# ------------------------------------------------------------------ predictors: a frame -> per-point predictions


@dataclass
class Predictions:
    """Per-point predictions for one frame (K points).

    xyz: (K,3) float metres; class_probs: (K,C+1) float, column 0 background, column c object ``class_ids[c-1]``;
    class_ids: C object ids; control_points: (K,9,3) float metres (point + offsets); confidence: (K,) in [0,1];
    timings: seconds spent, e.g. {"sampling", "network"}.
    """

    xyz: np.ndarray
    class_probs: np.ndarray
    class_ids: list[int]
    control_points: np.ndarray
    confidence: np.ndarray
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
                           frame.control_points[rows].astype(np.float64), np.ones(len(rows)))

    return predict


def network_predictor(checkpoint, seed: int = 0, device: str | None = None) -> Predictor:
    """A predictor running ``checkpoint.model`` (a :class:`detector.checkpoint.Checkpoint`) on one frame.

    Sampling and neighbour indices as in training (``detector.data.inference_batch``); times "sampling" and
    "network" (synchronised on GPU). On a GPU the neighbour indices are computed by the model (inside "network").
    """
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
                           xyz[:, None, :] + offsets, out["confidence"][0].double().cpu().numpy(),
                           {"sampling": t1 - t0, "network": t2 - t1})

    return predict


def estimate(preds: Predictions, objects: ObjectInfo, cfg: PoseConfig, timings: dict | None = None,
             cloud: np.ndarray | None = None, poser=None, features: np.ndarray | None = None
             ) -> tuple[list[Detection], list[Detection] | None]:
    """Detections of one frame without and (when ``cfg.icp``) with ICP refinement; stage seconds into ``timings``.

    cloud: (M,3) metres, the frame's full point cloud, for ICP (see :func:`detector.pose.refine`); None: the
    predicted points only. poser: a two-stage model's stage 2 (:class:`CropPoser`), called with
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


# ------------------------------------------------------------------------- a checkpoint's pose stage settings


def checkpoint_objects(ckpt) -> tuple[ObjectInfo, dict[int, str]]:
    """The pose-stage object info and names of a checkpoint's object table."""
    o = ckpt.objects
    return ObjectInfo.from_table(o), {int(i): str(n) for i, n in zip(o["ids"], o["names"])}


def check_label_objects(ckpt, table) -> None:
    """A label file to score a checkpoint on must show it objects it learned: the two share at least one object
    id, and a shared id is the same object (same diameter, to 0.1 %; ids alone say little: the built-in stand-ins
    and the LineMOD objects share ids 1-5). table: the label file's ``argen.h5.ObjectTable``. Objects that only the
    label file has are allowed (a test set of more objects); their instances count as missed."""
    o = ckpt.objects
    learned = {int(i): (str(n), float(d)) for i, n, d in zip(o["ids"], o["names"], o["diameters"])}
    shared = [int(i) for i in table.ids if int(i) in learned]
    if not shared:
        raise DetectorError("the label file shares no object with the model (label file: "
                            f"{', '.join(f'{n} ({int(i)})' for i, n in zip(table.ids, table.names))}; model: "
                            f"{', '.join(f'{n} ({i})' for i, (n, _) in learned.items())})")
    for i, n, d in zip(table.ids, table.names, table.diameters):
        if int(i) in learned and abs(float(d) - learned[int(i)][1]) > 1e-3 * learned[int(i)][1]:
            name, dia = learned[int(i)]
            raise DetectorError(f"object {int(i)} of the label file ({n}, diameter {1000 * float(d):.1f} mm) is not "
                                f"the model's object {int(i)} ({name}, {1000 * dia:.1f} mm)")


def pose_config(tau: float, icp: bool, base: PoseConfig | None = None) -> PoseConfig:
    """A PoseConfig from CLI options, checked; ``base`` gives the other settings."""
    if not 0 <= tau <= 1:
        raise DetectorError(f"--tau must be in [0, 1], got {tau}")
    return replace(base or PoseConfig(), tau=tau, icp=icp)


def checkpoint_pose_config(ckpt, tau: float | None, icp: bool, min_score: float | None = None) -> PoseConfig:
    """The pose settings of a checkpoint (those stored with a two-stage model, e.g. its thresholds), with the CLI's
    options over them; ``tau`` / ``min_score`` None keep the model's (the paper's tau 0.8 and no score threshold
    for a model that stores none)."""
    try:
        base = replace(PoseConfig(), **ckpt.pose_config)
    except TypeError as exc:
        raise DetectorError(f"the checkpoint's pose settings are not understood ({exc})") from None
    if min_score is not None:
        if not 0 <= min_score <= 1:
            raise DetectorError(f"--min-score must be in [0, 1], got {min_score}")
        base = replace(base, min_score=min_score)
    return pose_config(base.tau if tau is None else tau, icp, base)


def checkpoint_poser(ckpt, objects: ObjectInfo, device: str = "cpu", seed: int = 0):
    """A two-stage checkpoint's stage 2 (:class:`CropPoser`), or None for a single network."""
    if ckpt.pose_net is None:
        return None
    p = ckpt.pose
    support = float(ckpt.pose_config.get("support_distance", PoseConfig.support_distance))
    floor = float(ckpt.pose_config.get("support_floor", PoseConfig.support_floor))
    stored = {k: v for k, v in (p.get("infer_config") or {}).items() if k not in RETIRED_INFER_KEYS}
    try:
        cfg = CropPoseConfig(**stored)
    except TypeError as exc:
        raise DetectorError(f"the checkpoint's stage-2 settings are not understood ({exc})") from None
    return CropPoser(ckpt.pose_net, p["class_ids"], objects, CropConfig.from_dict(p["crop_config"]),
                     p["normalisation"], cfg, device, seed, support, floor)
