"""Which way round: an object whose shape looks the same under some turns (a printed box turned half way about an
axis) gets from depth, ICP included, a pose that fits the points equally well in each of those turns; only its print
tells them apart. :func:`colour_checked` poses each such detection in every turn its shape allows
(``ObjectInfo.shape_symmetries``, from :func:`argen.models.texture.shape_symmetries`) and keeps the one whose
model colours (``ObjectInfo.texture``) best match the colours the frame shows on the detection's points.

The match is made to survive another camera's colours: each side's colours are divided by their own mean per channel
(a white balance and an exposure cancel), and every frame point is compared with the colour of the model point
nearest to it under the turned pose, so every observed point counts once, wherever the model's samples lie. Numpy
and scipy; metres; poses map model into camera points (``x_cam = R @ x_model + t``).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from detector.geometry.icp import fit_residuals, fit_rms, refine_turned, support_radius, turned_poses

#: Fewest frame points matched to the model's print for a turn to be scored.
MIN_MATCHED = 30
#: A turn is a candidate when its trimmed point-to-plane RMS is within this fraction of the diameter of the best
#: turn's: the shape symmetries are exact only to a scan's tolerance, and depth decides between turns that differ
#: by more.
FIT_SLACK = 0.01


def colour_match(points: np.ndarray, colours: np.ndarray, R: np.ndarray, t: np.ndarray, texture_tree: cKDTree,
                 texture_colours: np.ndarray, radius: float) -> tuple[float, int]:
    """How well the model's print under the pose (R (3,3), t (3,) metres) matches the frame's colours at its points.

    points: (S,3) camera frame, metres; colours: (S,3) RGB in [0, 1]; texture_tree: cKDTree of the model's texture
    points (N,3) model frame, metres; texture_colours: (N,3) RGB in [0, 1]; radius: metres, a frame point farther
    from every texture point is not compared. Each side's matched colours are divided by their per-channel means;
    the score is minus their mean absolute difference (0 = the same up to a per-channel gain). Returns (score, number
    of points compared); (-inf, n) when fewer than ``MIN_MATCHED`` or the frame has no colour there."""
    q = (np.asarray(points, np.float64) - t) @ np.asarray(R, np.float64)  # model frame
    d, j = texture_tree.query(q, distance_upper_bound=radius)
    ok = np.isfinite(d)
    n = int(ok.sum())
    if n < MIN_MATCHED:
        return -np.inf, n
    a, b = np.asarray(colours, np.float64)[ok], texture_colours[j[ok]]
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    if ma.max() < 1e-3 or mb.max() < 1e-3:  # a frame (or a print) without colour tells nothing
        return -np.inf, n
    return -float(np.abs(a / np.maximum(ma, 1e-3) - b / np.maximum(mb, 1e-3)).mean()), n


def colour_checked(detections: list, cloud: np.ndarray, colours: np.ndarray, objects, cfg, icp: bool,
                   timings: dict | None = None) -> list:
    """Copies of ``detections`` (:class:`detector.geometry.types.Detection`) of objects with a print and shape
    symmetries, each turned to the candidate its print matches best (:func:`colour_match`); others unchanged.

    cloud: (M,3) camera frame, metres, the frame's points; colours: (M,3) RGB in [0, 1], theirs. Only a detection that
    carries ``points`` (rows of ``cloud``: a two-stage model's) is checked. Candidates: the pose and its turns whose
    trimmed fit to those points (:func:`detector.geometry.icp.fit_rms`) is within ``FIT_SLACK`` x diameter of the
    best; colours are compared within twice the support distance. With ``icp``, a turned pose is refined by ICP from
    there alone, on the points ICP takes (:func:`detector.geometry.icp.refine_pose`, :func:`icp_points`; a start
    turned half way could undo the choice), and a two-stage detection's score recomputed (its support, all points):
    :func:`detector.geometry.icp.refine_turned`.
    Adds "colour_check" seconds."""
    t0 = time.perf_counter()
    out = list(detections)
    cloud, colours = np.asarray(cloud, np.float64), np.asarray(colours, np.float64)
    for k, d in enumerate(detections):
        if d.obj_id not in objects.texture or d.points is None or len(d.points) < MIN_MATCHED:
            continue
        tex_tree, tex_cols = objects.texture_tree(d.obj_id)
        dia = objects.diameters[d.obj_id]
        radius = support_radius(cfg.support_distance, cfg.support_floor, dia)
        pts, cols = cloud[d.points], colours[d.points]
        Rk, tk = turned_poses(d.R, d.t, objects.shape_symmetries[d.obj_id])
        tree, normals = objects.surface(d.obj_id)
        fits = np.array([fit_rms(r, cfg.icp_trim) for r in fit_residuals(pts, tree, normals, Rk, tk,
                                                                          cfg.icp_gate * dia)])
        cand = np.flatnonzero(fits <= fits.min() + FIT_SLACK * dia)
        scores = [colour_match(pts, cols, Rk[c], tk[c], tex_tree, tex_cols, 2 * radius)[0] for c in cand]
        if not np.isfinite(max(scores)):
            continue
        best = int(cand[int(np.argmax(scores))])
        if best == 0:
            continue
        R, t, score = Rk[best], tk[best], d.score
        if icp:
            R, t, score = refine_turned(pts, d.obj_id, R, t, objects, cfg)
        out[k] = replace(d, R=R, t=t, score=score)
    if timings is not None:
        timings["colour_check"] = timings.get("colour_check", 0.0) + time.perf_counter() - t0
    return out
