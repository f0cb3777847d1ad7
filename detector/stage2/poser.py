"""Stage 2 at inference: for each stage-1 detection (an object and its centre) the crop network
(:mod:`detector.stage2.network`) labels the crop's points as the object's or not and regresses their model
coordinates; RANSAC over 3-point Kabsch hypotheses (:func:`detector.geometry.kabsch.ransac_kabsch`) turns the
foreground correspondences into a pose, optionally verified by the fit of the model surface. The crop may be cut
again around the new centre and the pose recomputed (``recentre``), which forgives a larger stage-1 centre error."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from detector.data.augment import reads_colour
from detector.errors import DetectorError
from detector.geometry.icp import fit_residuals, fit_rms, support_radius, surface_support
from detector.geometry.kabsch import ransac_draws, ransac_kabsch
from detector.geometry.types import Detection
from detector.geometry.workers import map_threads
from detector.net_dtype import check_net_dtype, net_autocast
from detector.stage2.colour_level import level_gain, levelled
from detector.stage2.crops import CropConfig, ball_rows, crop_input, roll_crop_input, sample_crop


@dataclass
class PoserConfig:
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
    is that many times larger, and so would their cost be); the refits use them all; colour_level: the crops after the
    first are cut from the frame's colours brought to the level the asked object had in the training frames, by the
    gain its first crop's foreground shows (:mod:`detector.stage2.colour_level`: another camera's exposure; needs the
    model's ``colour_levels``, no effect on a network without colour input or with ``recentre`` 0)."""

    fg_threshold: float = 0.5
    inlier: float = 0.05
    hypotheses: int = 128
    min_fg: int = 8
    recentre: int = 1
    samples: int = 1
    verify: int = 16
    verify_trim: float = 0.7
    fit_points: int = 256
    roll_deg: float = 0.0
    colour_level: bool = False

    def __post_init__(self):
        counts = {"hypotheses": 1, "samples": 1, "verify": 1, "recentre": 0, "min_fg": 3, "fit_points": 3}
        for key, least in counts.items():
            if getattr(self, key) < least:
                raise DetectorError(f"infer.{key} must be at least {least}, got {getattr(self, key)}")
        for key in ("fg_threshold", "verify_trim"):
            if not 0 < getattr(self, key) <= 1:
                raise DetectorError(f"infer.{key} is a share in (0, 1], got {getattr(self, key)}")
        if not self.inlier > 0:
            raise DetectorError(f"infer.inlier is a positive share of the diameter, got {self.inlier}")
        if not 0 <= self.roll_deg <= 90:
            raise DetectorError(f"infer.roll_deg is in degrees within [0, 90], got {self.roll_deg}")


#: PoserConfig keys that model files may hold but that are gone: ``recentre_min_shift`` limited the third and
#: later crops, which no model cuts any more (checkpoints/lm8.pt stores 0.04 with ``recentre`` 1: no effect).
RETIRED_INFER_KEYS = ("recentre_min_shift",)


def crop_subsets(rows: np.ndarray, num_points: int, samples: int, rng: np.random.Generator) -> list[np.ndarray]:
    """``samples`` subsets of a crop's rows (k,), each of ``num_points`` rows (:func:`detector.stage2.crops.sample_crop`):
    disjoint while the crop has enough points, then drawn independently. One subset is ``sample_crop``'s."""
    if samples <= 1:
        return [sample_crop(rows, num_points, rng)]
    perm = rng.permutation(rows)
    return [np.sort(perm[s * num_points:(s + 1) * num_points]) if (s + 1) * num_points <= len(rows)
            else sample_crop(rows, num_points, rng) for s in range(samples)]


def subset_rolls(samples: int, roll_deg: float) -> np.ndarray:
    """The roll in radians (samples,) of each of a crop's ``samples`` subsets: evenly spread over [-roll_deg,
    roll_deg] degrees; none for one subset or ``roll_deg`` 0."""
    if samples <= 1 or roll_deg == 0:
        return np.zeros(max(samples, 1))
    return np.deg2rad(np.linspace(-roll_deg, roll_deg, samples))


@torch.no_grad()
def crop_predictions(net, features: np.ndarray, centres: np.ndarray, classes: np.ndarray, diameters: np.ndarray,
                     crop_cfg: CropConfig, normalisation: dict, seed: int = 0, device="cpu", samples: int = 1,
                     roll_deg: float = 0.0, gains: Sequence[float] | None = None, net_dtype: str = "float32"):
    """Run the crop network on ``samples`` point subsets (:func:`crop_subsets`) of one crop per centre, subset k
    rolled about the camera ray through the centre by :func:`subset_rolls`' k-th angle.

    features: (N,9) the frame's label features; centres: (D,3) metres; classes: (D,) class indices;
    diameters: (D,) metres; roll_deg: degrees; gains: (D,) each crop's colours are first multiplied by its gain
    (:func:`detector.stage2.colour_level.levelled`; None: as they are); net_dtype: the network's number format,
    resolved (:func:`detector.net_dtype.resolve_net_dtype`). Returns a list of D (rows (m,) into
    features, fg probability (m,), model coordinates (m,3) metres), the subsets' predictions one after the other
    (m = samples x ``crop_cfg.num_points``), or None where the crop holds fewer than ``crop_cfg.min_points`` points.
    """
    xyz = np.asarray(features[:, :3], np.float64)
    rng = np.random.default_rng(seed)
    rolls = subset_rolls(samples, roll_deg)
    batch, keep, out = [], [], [None] * len(centres)
    for k, (c, dia) in enumerate(zip(centres, diameters)):
        rows = ball_rows(xyz, c, crop_cfg.radius * dia)
        if len(rows) < crop_cfg.min_points:
            continue
        for sub, roll in zip(crop_subsets(rows, crop_cfg.num_points, samples, rng), rolls):
            if gains is None or gains[k] == 1.0:
                feats = crop_input(features, sub, c, crop_cfg.radius * dia, normalisation)
            else:
                feats = crop_input(levelled(np.asarray(features)[sub], gains[k]), np.arange(len(sub)), c,
                                   crop_cfg.radius * dia, normalisation)
            batch.append(roll_crop_input(feats, c, roll))
            keep.append((k, sub))
    if not batch:
        return out
    feats = torch.from_numpy(np.stack(batch)).to(device)
    cls = torch.as_tensor(np.asarray(classes)[[k for k, _ in keep]], dtype=torch.int64, device=device)
    with net_autocast(net_dtype):
        res = net(feats, cls)
    prob = torch.sigmoid(res["fg_logit"].float()).cpu().numpy()
    coords = res["coords"].double().cpu().numpy()
    pooled: dict[int, list] = {}
    for j, (k, rows) in enumerate(keep):
        pooled.setdefault(k, []).append((rows, prob[j], coords[j] * diameters[k]))
    for k, parts in pooled.items():
        out[k] = tuple(np.concatenate(z) for z in zip(*parts))
    return out


def pose_draws(num_fg: int, cfg: PoserConfig, rng: np.random.Generator, verify: bool) -> tuple | None:
    """The random choices :func:`pose_from_crop` makes for a crop of ``num_fg`` foreground points, in its order:
    RANSAC's (:func:`detector.geometry.kabsch.ransac_draws`) and, with ``verify``, the foreground rows the
    verification measures the fits on, test (m,) int64 (at most ``cfg.fit_points``, a random subset, sorted).
    Returns (sub, idx, test or None), or None where the crop has too few foreground points for a pose (nothing
    drawn). Drawing them before the fits lets a frame's crops be posed on threads with the results of one thread."""
    if num_fg < max(cfg.min_fg, 3):
        return None
    sub, idx = ransac_draws(num_fg, cfg.hypotheses, rng, cfg.fit_points)
    if not verify:
        return sub, idx, None
    test = np.arange(num_fg) if num_fg <= cfg.fit_points else \
        np.sort(rng.choice(num_fg, cfg.fit_points, replace=False))
    return sub, idx, test


def pose_from_crop(xyz: np.ndarray, prob: np.ndarray, model_xyz: np.ndarray, diameter: float, cfg: PoserConfig,
                   rng: np.random.Generator | None, surface=None, draws: tuple | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list] | None:
    """A pose from one crop's predictions: xyz (n,3) camera metres, prob (n,), model_xyz (n,3) model metres.

    surface: (cKDTree of model points, normals) for ``cfg.verify`` > 1 (:meth:`detector.geometry.types.ObjectInfo.surface`).
    draws: :func:`pose_draws`' choices for this crop, drawn before (``rng`` is then not used); None: drawn here
    from ``rng``. Returns R (3,3), t (3,), the foreground (probability >= ``cfg.fg_threshold``) indices of the crop
    and the other verified hypotheses [(R, t), ...] from the best fit to the worst (empty without verification), or
    None with fewer than ``cfg.min_fg`` foreground points.
    """
    fg = np.flatnonzero(prob >= cfg.fg_threshold)
    keep = cfg.verify if surface is not None else 1
    if draws is None:
        draws = pose_draws(len(fg), cfg, rng, keep > 1)
    if draws is None:
        return None
    sub, idx, test = draws
    cands = ransac_kabsch(model_xyz[fg], xyz[fg], prob[fg], cfg.inlier * diameter, None, keep=keep,
                          draws=(sub, idx))
    if keep > 1:
        tree, normals = surface
        res = fit_residuals(xyz[fg[test]], tree, normals, np.stack([c[0] for c in cands]),
                            np.stack([c[1] for c in cands]), 0.05 * diameter)  # (verify, n): all hypotheses at once
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
    stage's :class:`detector.geometry.types.ObjectInfo`; crop_cfg / cfg: crop and pose options; normalisation: colour
    normalisation of the network input. Calling it with (detections, features (N,9), timings) returns the
    detections with stage-2 poses, scores, ``points`` = the crop's foreground rows of ``features`` (ICP uses
    them) and ``alternatives`` = the crop's other verified hypotheses, best fit first (ICP may start from them). A detection whose crop yields no pose is dropped. Adds "stage2" seconds. The score is the share of the
    foreground points that the model surface under the pose explains to within ``support_distance`` of the
    diameter, but at least ``support_floor`` metres (:func:`detector.geometry.icp.surface_support`): it tells wrong poses and false detections from right ones
    far better than vote or inlier shares (measured on a validation capture). colour_levels: {object id: (3,) RGB
    level in the training frames or None}, the model's (``cfg.colour_level``); None: none known (the option then has
    no effect: :func:`detector.infer.checkpoint_poser` refuses it for a model file without them); net_dtype: the
    network's number format, resolved (:func:`detector.net_dtype.resolve_net_dtype`: float32 or bfloat16).
    """

    def __init__(self, net, class_ids: list[int], objects, crop_cfg: CropConfig, normalisation: dict,
                 cfg: PoserConfig | None = None, device="cpu", seed: int = 0, support_distance: float = 0.02,
                 support_floor: float = 0.0, colour_levels: dict | None = None, net_dtype: str = "float32"):
        self.net, self.class_ids, self.objects = net, list(class_ids), objects
        self.support_distance, self.support_floor = support_distance, support_floor
        self.crop_cfg, self.normalisation, self.cfg = crop_cfg, normalisation, cfg or PoserConfig()
        self.device, self.seed = device, seed
        check_net_dtype(net_dtype, device)  # a bad value fails here, not at the first crop
        self.net_dtype = net_dtype
        self.colour_levels = colour_levels if self.cfg.colour_level and reads_colour(normalisation) else None

    def _run(self, features, centres, oids, samples: int = 1, gains=None):
        classes = np.array([self.class_ids.index(o) for o in oids], np.int64)
        dia = np.array([self.objects.diameters[o] for o in oids], np.float64)
        return crop_predictions(self.net, features, np.asarray(centres), classes, dia, self.crop_cfg,
                                self.normalisation, self.seed, self.device, samples, self.cfg.roll_deg, gains,
                                self.net_dtype)

    def __call__(self, detections: list[Detection], features: np.ndarray, timings: dict | None = None
                 ) -> list[Detection]:
        t0 = time.perf_counter()
        dets = [d for d in detections if d.obj_id in self.class_ids]
        xyz = np.asarray(features[:, :3], np.float64)
        rng = np.random.default_rng(self.seed)
        centres = [d.control_points[8] for d in dets]
        results: list = [None] * len(dets)  # (R, t, foreground rows of features, other hypotheses) of each detection
        gains = [1.0] * len(dets)  # each detection's colour gain for its crops after the first (cfg.colour_level)
        for it in range(1 + self.cfg.recentre):
            todo = [k for k in range(len(dets)) if it == 0 or results[k] is not None]
            if not todo:
                break
            preds = self._run(features, [centres[k] for k in todo], [dets[k].obj_id for k in todo],
                              1 if it == 0 else self.cfg.samples, [gains[k] for k in todo])
            jobs = []  # (detection, its crop's rows, fg probability, model coordinates, surface, draws)
            for k, pred in zip(todo, preds):
                if pred is None:
                    continue
                rows, prob, mxyz = pred
                fg = prob >= self.cfg.fg_threshold
                if it == 0 and self.colour_levels is not None:  # the level the frame shows of the asked object
                    gains[k] = level_gain(np.asarray(features)[np.unique(rows[fg]), 3:6],
                                          self.colour_levels.get(dets[k].obj_id))
                surface = self.objects.surface(dets[k].obj_id) if self.cfg.verify > 1 else None
                # the random choices in the crops' order here, the fits on threads: the results of one thread
                draws = pose_draws(int(np.count_nonzero(fg)), self.cfg, rng, surface is not None)
                if draws is not None:
                    jobs.append((k, rows, prob, mxyz, surface, draws))

            def fit(job):
                k, rows, prob, mxyz, surface, draws = job
                return pose_from_crop(xyz[rows], prob, mxyz, self.objects.diameters[dets[k].obj_id], self.cfg, None,
                                      surface, draws)

            for (k, rows, _, _, _, _), res in zip(jobs, map_threads(fit, jobs)):
                R, t, fg, others = res
                results[k] = (R, t, np.unique(rows[fg]), others)
                centres[k] = R @ self.objects.control_points[dets[k].obj_id][8] + t
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
