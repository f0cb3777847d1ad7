"""Inference: a checkpoint (or the ground truth, as an oracle) -> per-point predictions -> poses.

The one place where the two stages meet at inference. A predictor (:mod:`detector.stage1.predictor`) maps a frame
to per-point predictions; :func:`estimate` turns them into detections with :mod:`detector.geometry` (voting, Kabsch,
ICP) and, for a two-stage model, stage 2's :class:`detector.stage2.poser.CropPoser`, which replaces each
detection's pose by one from the crop network's mask and model coordinates. The ``checkpoint_*`` helpers read a
checkpoint's objects, geometry settings and stage 2. ``detector eval`` and ``detector predict`` both infer through
this module.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from argen.features import check_max_depth
from detector.config import apply_set_options, parse_set_options
from detector.data.augment import reads_colour
from detector.data.plane import dominant_plane
from detector.errors import DetectorError, argen_errors
from detector.geometry.colour_check import colour_checked
from detector.geometry.icp import refine
from detector.geometry.part_check import part_checked
from detector.geometry.types import Detection, GeometryConfig, ObjectInfo
from detector.geometry.verify import continuation_checked, depth_checked, pose_consistency, range_image
from detector.geometry.voting import detect, nms, other_classes
from detector.stage1.predictor import Predictions
from detector.stage2.crops import CropConfig
from detector.stage2.poser import CropPoser, PoserConfig, RETIRED_INFER_KEYS


#: The model points on which the frame's depth chooses among a detection's ICP results (at most about this many:
#: its cost grows with them; the depth check itself measures on all of them).
CHOICE_POINTS = 250


def estimate(preds: Predictions, objects: ObjectInfo, cfg: GeometryConfig, timings: dict | None = None,
             cloud: np.ndarray | None = None, poser=None, features: np.ndarray | None = None,
             check_unrefined: bool = False) -> tuple[list[Detection], list[Detection] | None]:
    """Detections of one frame without and (when ``cfg.icp``) with ICP refinement; stage seconds into ``timings``.

    cloud: (M,3) metres, the frame's full point cloud, for ICP (see :func:`detector.geometry.icp.refine`); None: the
    predicted points only. poser: a two-stage model's stage 2 (:class:`detector.stage2.poser.CropPoser`), called with
    the stage-1 detections, each also as the other objects its points make likely enough (``cfg.other_classes``:
    :func:`detector.geometry.voting.other_classes`), and ``features`` (M,9), the frame's points whose xyz is
    ``cloud``; its detections are suppressed again (two crops may settle on one object). With ``cfg.depth_check``
    and a cloud, a score falls where the frame's depth contradicts the pose
    (:func:`detector.geometry.verify.depth_checked`; a two-stage detection's again after ICP, which rescored it,
    against ``cfg.depth_consistent_refined`` where that is set; a single network's once). ``cfg.min_score`` then
    drops the weak refined detections (by their score after ICP, recomputed there for a two-stage detection) and
    ``cfg.min_score_unrefined`` the weak unrefined ones; an other-class copy below that threshold is dropped before
    ICP (ICP lifts right poses of the stage-1 class from below it, measured; the copies are many and mostly wrong).
    With ``cfg.colour_check`` and ``features``, an
    object whose print breaks its shape's symmetries is turned to the way round its print matches
    (:func:`detector.geometry.colour_check.colour_checked`), before and after ICP. With ``cfg.part_check`` and a
    cloud, an object with a part symmetry is turned about its axis to where the frame's depth allows its odd part
    (:func:`detector.geometry.part_check.part_checked`): the poses after ICP, and the unrefined ones once ICP has
    started from them as they were (from a half-turned start ICP sometimes finds the turn itself, and a check before
    it would move such poses away: RESULTS.md). With ``cfg.icp_depth_margin`` and a cloud, the frame's depth also
    chooses among each detection's ICP results (:func:`detector.geometry.icp.chosen_result`). With
    ``cfg.continuation_check`` and a cloud, last, the score of a pose that would be kept falls where the frame's
    surfaces run on past its model (:func:`detector.geometry.verify.continuation_checked`: a pose on part of a
    larger thing; the frame's dominant plane, the table, counts as such only for a pose lying in it): the poses
    after ICP, and the unrefined ones where they are the output (without ICP) or ``check_unrefined`` asks for them
    (an evaluation that reports both). With ``cfg.nms_across_objects``, last, each list keeps one detection a place,
    whatever its object (:func:`detector.geometry.voting.nms`). Adds "depth_check" seconds (the range image's too)
    and "continuation_check" seconds.
    """
    dets = detect(preds.xyz, preds.obj_ids, preds.confidence, preds.control_points, objects, cfg, timings)
    if poser is not None:
        if cfg.other_classes <= 1:
            dets = other_classes(dets, preds.class_probs, preds.class_ids, objects, cfg.other_classes, cfg.nms_fraction)
        dets = poser(dets, features, timings)
    t0 = time.perf_counter()
    parts = cfg.part_check and cloud is not None and bool(objects.part_symmetries)
    choose = cfg.icp and cfg.icp_depth_margin is not None
    frame = range_image(cloud) if (cfg.depth_check or parts or choose) and cloud is not None else None
    if frame is not None and cfg.depth_check:
        dets = depth_checked(dets, frame, objects, cfg)
    t_check = time.perf_counter() - t0
    if poser is not None:
        dets = nms(dets, objects.diameters, cfg.nms_fraction, box_centres=objects.box_centres())
    lo = cfg.min_score if cfg.min_score_unrefined is None else cfg.min_score_unrefined
    dets = [d for d in dets if d.score >= lo or not d.other_class]  # a weak other-class copy is not worth an ICP
    colours = features[:, 3:6] if cfg.colour_check and features is not None and objects.texture else None
    consistency_of = (lambda oid, R, t: pose_consistency(frame, objects, cfg, oid, R, t, CHOICE_POINTS)) \
        if choose and frame is not None else None
    refined = refine(dets, preds.xyz, objects, cfg, timings, cloud, consistency_of) if cfg.icp else None
    if colours is not None:
        dets = colour_checked(dets, cloud, colours, objects, cfg, icp=False, timings=timings)
        if refined is not None:
            refined = colour_checked(refined, cloud, colours, objects, cfg, icp=True, timings=timings)
    if parts:  # the unrefined poses once ICP has started from them as they were
        dets = part_checked(dets, frame, cloud, objects, cfg, icp=False, timings=timings)
    if refined is not None and parts:
        refined = part_checked(refined, frame, cloud, objects, cfg, icp=True, timings=timings)
    if refined is not None and frame is not None and cfg.depth_check:  # ICP rescored the two-stage ones: again
        t0 = time.perf_counter()
        again = [k for k, d in enumerate(refined) if d.points is not None]
        for k, d in zip(again, depth_checked([refined[k] for k in again], frame, objects, cfg, refined=True)):
            refined[k] = d
        t_check += time.perf_counter() - t0
    if frame is not None and cfg.depth_check and timings is not None:
        timings["depth_check"] = timings.get("depth_check", 0.0) + t_check
    # the poses that would be kept, where the objects carry surface normals; the unrefined ones where they count
    check = [d for d in dets if d.score >= lo] if refined is None or check_unrefined else []
    check_refined = [d for d in refined if d.score >= cfg.min_score] if refined is not None else []
    if (cfg.continuation_check and cloud is not None and
            any(d.obj_id in objects.surfaces for d in check + check_refined)):
        t0 = time.perf_counter()
        xyz = np.asarray(cloud, np.float64)  # once: the plane and every pose's check read it
        # the surface the objects stand on: its points are not continued (a curved face meets it in its tangent
        # plane) unless a pose lies in it; the same draw every call, so a frame's poses are checked alike
        support = dominant_plane(xyz, np.random.default_rng(0))
        if refined is None or check_unrefined:
            dets = continuation_checked(check, xyz, objects, cfg, support)
        if refined is not None:
            refined = continuation_checked(check_refined, xyz, objects, cfg, support)
        if timings is not None:
            timings["continuation_check"] = timings.get("continuation_check", 0.0) + time.perf_counter() - t0
    dets = [d for d in dets if d.score >= lo]
    refined = [d for d in refined if d.score >= cfg.min_score] if refined is not None else None
    if cfg.nms_across_objects:  # one object a place: the scores, final now, choose among a place's objects
        centres = objects.box_centres()
        dets = nms(dets, objects.diameters, cfg.nms_fraction, True, centres)
        refined = nms(refined, objects.diameters, cfg.nms_fraction, True, centres) if refined is not None else None
    return dets, refined


def missing_surfaces(cfg: GeometryConfig, objects: ObjectInfo, model: str) -> str | None:
    """The warning for a model whose objects carry no surface normals while the surface-continuation check is on
    (``cfg.continuation_check``): nothing is checked. None where there is nothing to say. model: its name, for the
    message."""
    if not cfg.continuation_check or objects.surfaces:
        return None
    return (f"geometry.continuation_check is on, but {model} was trained without the objects' surface normals (label "
            "files written before 2026-12-07): nothing is checked (README: detector.checkpoint.add_surfaces adds them "
            "to the model file)")


def colour_networks(ckpt) -> list[str]:
    """The stages of a model whose networks take colour input: "stage 1", "stage 2" ([] for networks that see
    geometry only). ckpt: a loaded checkpoint (:func:`detector.checkpoint.load_checkpoint`)."""
    out = ["stage 1"] if reads_colour(ckpt.normalisation) else []
    if ckpt.stage2 is not None and reads_colour(ckpt.stage2.get("normalisation")):
        out.append("stage 2")
    return out


def colour_readers(ckpt, objects: ObjectInfo, cfg: GeometryConfig) -> list[str]:
    """What of a model reads a frame's colours: :func:`colour_networks`, and "the colour check" where it is on
    (``cfg.colour_check``) and an object carries a print to check (``objects.texture``). [] for a model that works
    on depth alone."""
    return colour_networks(ckpt) + (["the colour check"] if cfg.colour_check and objects.texture else [])


def checkpoint_max_depth(ckpt, given: float | None = None) -> float | None:
    """The working volume a frame's points are taken from, metres along z: ``given`` (``--max-depth``), else the
    one the model's stage 1 was trained in (its label file's ``max_depth``), else None (every point). A real frame's
    far background (walls, a room) was never in the training frames: beyond that volume it would draw points from
    the objects and look like nothing the network saw."""
    if given is not None:
        with argen_errors():
            return check_max_depth(given)
    depth = ckpt.extra.get("max_depth")
    return float(depth) if depth else None


def checkpoint_objects(ckpt) -> tuple[ObjectInfo, dict[int, str]]:
    """The geometry's object info and names of a checkpoint's object table."""
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


def geometry_config(tau: float, icp: bool, base: GeometryConfig | None = None) -> GeometryConfig:
    """A GeometryConfig from CLI options, checked; ``base`` gives the other settings."""
    if not 0 <= tau <= 1:
        raise DetectorError(f"--tau must be in [0, 1], got {tau}")
    base = base or GeometryConfig()
    if base.icp_depth_margin is not None and not 0 <= base.icp_depth_margin <= 1:
        raise DetectorError("geometry.icp_depth_margin is a consistency margin in [0, 1] or null, got "
                            f"{base.icp_depth_margin}")
    if not 0 <= base.icp_own_margin <= 1:
        raise DetectorError(f"geometry.icp_own_margin is a share in [0, 1], got {base.icp_own_margin}")
    for key in ("continuation_limit", "continuation_tolerance", "continuation_reach"):
        if not getattr(base, key) > 0:
            raise DetectorError(f"geometry.{key} must be above 0, got {getattr(base, key)}")
    if not base.continuation_gap >= 0:
        raise DetectorError(f"geometry.continuation_gap is metres, at least 0, got {base.continuation_gap}")
    return replace(base, tau=tau, icp=icp)


def split_sets(sets: list[str] | None) -> tuple[list[str], dict, dict]:
    """eval's and predict's ``--set`` options, ``["geometry.KEY=VALUE", "sampling.KEY=VALUE", "infer.KEY=VALUE",
    ...]``: (the geometry ones, for :func:`checkpoint_geometry_config`; the sampling ones as ``{"KEY": value}``, for
    :func:`detector.checkpoint.load_checkpoint`; the infer ones, stage 2's inference settings, as ``{"KEY": value}``,
    for :func:`checkpoint_poser`). Any other section is a one-line DetectorError."""
    geometry, sampling, infer = [], {}, {}
    for pair in sets or []:
        (key, value), = parse_set_options([pair]).items()
        head, _, rest = key.partition(".")
        if head == "sampling" and rest:
            sampling[rest] = value
        elif head == "infer" and rest:
            infer[rest] = value
        elif head == "geometry" and rest:
            geometry.append(pair)
        else:
            raise DetectorError(f"--set {key}: eval and predict take geometry, sampling and infer settings only "
                                "(--set geometry.KEY=VALUE, --set sampling.density=VALUE, --set sampling.passes=N, "
                                "--set sampling.fps=tree, --set infer.KEY=VALUE)")
    return geometry, sampling, infer


def checkpoint_geometry_config(ckpt, tau: float | None, icp: bool, min_score: float | None = None,
                               sets: list[str] | None = None) -> GeometryConfig:
    """The geometry settings of a checkpoint (those stored with a two-stage model, e.g. its thresholds), with the CLI's
    options over them; ``tau`` / ``min_score`` None keep the model's (the paper's tau 0.8 and no score threshold
    for a model that stores none); ``sets``: ``["geometry.KEY=VALUE", ...]`` (``--set``), any other
    :class:`GeometryConfig` setting, checked."""
    try:
        base = replace(GeometryConfig(), **ckpt.geometry_config)
    except TypeError as exc:
        raise DetectorError(f"the checkpoint's geometry settings are not understood ({exc})") from None
    dotted = parse_set_options(sets)
    for key in dotted:
        if not key.startswith("geometry."):
            raise DetectorError(f"--set {key}: not a geometry setting (--set geometry.KEY=VALUE)")
    if dotted:
        base = apply_set_options(base, {k.split(".", 1)[1]: v for k, v in dotted.items()}, "--set geometry")
    if min_score is not None:
        if not 0 <= min_score <= 1:
            raise DetectorError(f"--min-score must be in [0, 1], got {min_score}")
        base = replace(base, min_score=min_score)
    return geometry_config(base.tau if tau is None else tau, icp, base)


def checkpoint_poser(ckpt, objects: ObjectInfo, device: str = "cpu", seed: int = 0, sets: dict | None = None,
                     net_dtype: str = "float32"):
    """A two-stage checkpoint's stage 2 (:class:`detector.stage2.poser.CropPoser`), or None for a single network.
    sets: ``{"KEY": value}`` over the model's stored stage-2 inference settings (keys of
    :class:`detector.stage2.poser.PoserConfig`, e.g. RANSAC's ``hypotheses``; ``--set infer.KEY=VALUE``); an
    unknown key, a bad value or settings for a model without stage 2 is a one-line DetectorError. net_dtype: its
    network's number format, resolved (:func:`detector.net_dtype.resolve_net_dtype`)."""
    if ckpt.stage2_net is None:
        if sets:
            raise DetectorError(f"--set infer.{next(iter(sets))}: this model has no stage 2 (a single network)")
        return None
    p = ckpt.stage2
    support = float(ckpt.geometry_config.get("support_distance", GeometryConfig.support_distance))
    floor = float(ckpt.geometry_config.get("support_floor", GeometryConfig.support_floor))
    stored = {k: v for k, v in (p.get("infer_config") or {}).items() if k not in RETIRED_INFER_KEYS}
    try:
        cfg = PoserConfig(**stored)
    except TypeError as exc:
        raise DetectorError(f"the checkpoint's stage-2 settings are not understood ({exc})") from None
    if sets:
        cfg = apply_set_options(cfg, sets, "--set infer")  # types checked; PoserConfig checks the ranges
    levels = p.get("colour_levels")
    if cfg.colour_level and reads_colour(p.get("normalisation")) and levels is None:
        raise DetectorError("infer.colour_level needs the colour levels of the model's training frames, which this "
                            "model file lacks (README: detector.checkpoint.add_colour_levels adds them)")
    return CropPoser(ckpt.stage2_net, p["class_ids"], objects, CropConfig.from_dict(p["crop_config"]),
                     p["normalisation"], cfg, device, seed, support, floor,
                     dict(zip((int(i) for i in p["class_ids"]), levels)) if levels is not None else None, net_dtype)
