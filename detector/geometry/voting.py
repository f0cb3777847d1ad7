"""From per-point network output to detections (paper section "6-DOF Pose Estimation").

Pipeline: drop background points and points with confidence under ``tau``; each kept point's control
points = point + offsets; per class, the predicted box centres vote, and the votes form instances (so several
instances of one object are found): connected occupied cells of a voxel grid (:func:`vote_clusters`), or with
``mode_radius`` > 0 the votes around their density modes (:func:`vote_modes`); a robust aggregate of the
instance's votes is fitted to the model's 9 control points with a confidence-weighted, reflection-safe Kabsch
(:mod:`detector.geometry.kabsch`); non-maximum suppression by confidence. With ``centre_votes`` (a two-stage
model's stage 1) only the centre is found and stage 2 gives the orientation. ICP follows in
:mod:`detector.geometry.icp`.

Numpy and scipy; metres; poses map model points into the camera frame (``x_cam = R @ x_model + t``).
"""

from __future__ import annotations

from dataclasses import replace

import time

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
from scipy.spatial import cKDTree

from detector.geometry.kabsch import kabsch
from detector.geometry.types import Detection, GeometryConfig, ObjectInfo


# the 27 offsets of a voxel's 26-neighbourhood (and itself)
_NEIGHBOURS = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)


def keep_mask(obj_ids: np.ndarray, confidence: np.ndarray, tau: float) -> np.ndarray:
    """Points that are foreground and at least ``tau`` confident. obj_ids: (K,) int, 0 = background; confidence: (K,)."""
    return (np.asarray(obj_ids) > 0) & (np.asarray(confidence) >= tau)


def vote_clusters(centres: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Cluster votes: occupied voxels of size ``cell`` that touch (26-neighbourhood) form one cluster.

    centres: (V,3) metres. Returns labels (V,) int64 cluster of each vote, counts (C,) int64 votes per cluster.
    """
    centres = np.asarray(centres, np.float64)
    if len(centres) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    keys = np.floor(centres / cell).astype(np.int64)
    cells, vote_cell = np.unique(keys, axis=0, return_inverse=True)
    vote_cell = vote_cell.reshape(-1)
    lo = cells.min(0) - 1
    dims = cells.max(0) + 2 - lo
    flat = np.ravel_multi_index((cells - lo).T, dims)  # sorted, since cells are sorted lexicographically
    nb = cells[:, None, :] + _NEIGHBOURS[None]  # (U,27,3)
    nb_flat = np.ravel_multi_index((nb - lo).reshape(-1, 3).T, dims)
    pos = np.clip(np.searchsorted(flat, nb_flat), 0, len(flat) - 1)
    hit = flat[pos] == nb_flat
    src = np.repeat(np.arange(len(cells)), len(_NEIGHBOURS))[hit]
    graph = scipy.sparse.coo_matrix((np.ones(hit.sum()), (src, pos[hit])), shape=(len(cells), len(cells)))
    _, cell_label = scipy.sparse.csgraph.connected_components(graph, directed=False)
    labels = cell_label[vote_cell].astype(np.int64)
    return labels, np.bincount(labels).astype(np.int64)


def vote_modes(centres: np.ndarray, weights: np.ndarray, radius: float, min_votes: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """Cluster votes around their density modes: from the vote with the most votes within ``radius`` among the
    unassigned ones, mean-shift (flat kernel of ``radius``, weighted) to a mode, and give the mode every unassigned
    vote within ``radius``; repeat while a mode gathers at least ``min_votes``. Unlike touching voxels
    (:func:`vote_clusters`), two objects whose vote clouds touch stay two clusters.

    centres: (V,3) metres; weights: (V,) >= 0; radius: metres. Returns labels (V,) int64 (-1 for votes of no
    cluster) and counts (C,) int64 votes per cluster.
    """
    centres = np.asarray(centres, np.float64)
    w = np.asarray(weights, np.float64) + 1e-12
    labels = np.full(len(centres), -1, np.int64)
    if len(centres) == 0:
        return labels, np.zeros(0, np.int64)
    density = cKDTree(centres).query_ball_point(centres, radius, return_length=True)
    order = np.argsort(-density, kind="stable")
    free = np.ones(len(centres), bool)
    counts: list[int] = []
    r2 = radius * radius
    while True:
        seeds = order[free[order]]
        if len(seeds) < min_votes:
            break
        m = centres[seeds[0]]
        for _ in range(20):
            near = free & (np.sum((centres - m) ** 2, axis=1) < r2)
            new = w[near] @ centres[near] / w[near].sum()
            done = np.sum((new - m) ** 2) < 1e-8 * r2
            m = new
            if done:
                break
        near = free & (np.sum((centres - m) ** 2, axis=1) < r2)
        if near.sum() < min_votes:
            free[seeds[0]] = False  # a sparse seed: no cluster around it
            continue
        labels[near] = len(counts)
        counts.append(int(near.sum()))
        free &= ~near
    return labels, np.asarray(counts, np.int64)


def robust_control_points(votes: np.ndarray, weights: np.ndarray, diameter: float,
                          inlier_fraction: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    """A robust aggregate of control-point votes: weighted mean of the votes near the per-coordinate median.

    votes: (V,9,3) metres; weights: (V,) >= 0; diameter: object diameter, metres. A vote is an inlier when its
    mean distance to the median control points is under ``inlier_fraction * diameter`` (the median itself is
    used when no vote is). Returns control points (9,3) float64 metres, inlier mask (V,) bool.
    """
    votes = np.asarray(votes, np.float64)
    med = np.median(votes, axis=0)
    dist = np.linalg.norm(votes - med, axis=2).mean(1)
    inl = dist < inlier_fraction * diameter
    w = np.asarray(weights, np.float64) * inl
    if w.sum() <= 0:
        return med, inl
    return np.einsum("v,vij->ij", w, votes) / w.sum(), inl


def nms(detections: list[Detection], diameters: dict[int, float], fraction: float,
        across_objects: bool = False, box_centres: dict[int, np.ndarray] | None = None) -> list[Detection]:
    """Non-maximum suppression by score: drop a detection whose centre lies within ``fraction`` of the
    object's diameter (metres, per obj_id) of a higher-scoring detection of the same object. ``across_objects``:
    also of a higher-scoring detection of another object, within ``fraction`` of the smaller of the two diameters
    (two solid objects do not share a place; a two-stage model poses one stage-1 detection as several objects,
    :func:`other_classes`, and the scores choose among them). A detection's centre is its model origin ``t``, or
    with ``box_centres`` (per obj_id, (3,) metres in the model frame: ``ObjectInfo.control_points[obj_id][8]``) its
    posed box centre ``R @ c + t``: a mesh's origin may lie anywhere (at its base, at a corner), and two objects'
    origins say little of where they stand. Returns kept, by score."""
    def centre(d: Detection) -> np.ndarray:
        return d.t if box_centres is None else np.asarray(d.R) @ box_centres[d.obj_id] + d.t

    kept: list[tuple[Detection, np.ndarray]] = []
    for d in sorted(detections, key=lambda d: -d.score):
        c = centre(d)
        if all(np.linalg.norm(kc - c) >= fraction * (diameters[d.obj_id] if k.obj_id == d.obj_id else
                                                     min(diameters[d.obj_id], diameters[k.obj_id]))
               for k, kc in kept if across_objects or k.obj_id == d.obj_id):
            kept.append((d, c))
    return [d for d, _ in kept]


def other_classes(detections: list[Detection], class_probs: np.ndarray, class_ids: list[int], objects: ObjectInfo,
                  min_prob: float, fraction: float) -> list[Detection]:
    """The detections and, for each, a copy as every other object whose class the detection's points give a mean
    probability of at least ``min_prob``, centred on the same box centre (orientation left to stage 2), unless a
    detection of that object already lies within ``fraction`` of its diameter. On real frames the first stage's
    classes are often wrong where its centres are right (a brick taken for a box); stage 2 then poses each class and
    the scores tell them apart. class_probs: (K,C+1) per predicted point, column 0 background, column c object
    ``class_ids[c-1]``; a detection's ``members`` index its rows. A copy's score is the detection's times that
    probability; it is marked ``other_class``. ``min_prob`` > 1: none."""
    out = list(detections)
    for d in detections:
        mean = np.asarray(class_probs, np.float64)[d.members].mean(axis=0)
        centre = d.control_points[8]
        for c, oid in enumerate(class_ids):
            oid = int(oid)
            if oid == d.obj_id or oid not in objects.diameters or mean[c + 1] < min_prob:
                continue
            t = centre - objects.control_points[oid][8]
            if any(k.obj_id == oid and np.linalg.norm(k.t - t) < fraction * objects.diameters[oid] for k in out):
                continue
            out.append(replace(d, obj_id=oid, t=t, R=np.eye(3), control_points=objects.control_points[oid] + t,
                               score=float(d.score * mean[c + 1]), other_class=True))
    return out


def detect(xyz: np.ndarray, obj_ids: np.ndarray, confidence: np.ndarray, control_points: np.ndarray,
           objects: ObjectInfo, cfg: GeometryConfig, timings: dict | None = None) -> list[Detection]:
    """Instances and their Kabsch poses from per-point predictions (no ICP).

    xyz: (K,3) metres; obj_ids: (K,) int predicted object id, 0 = background; confidence: (K,) in [0,1];
    control_points: (K,9,3) metres camera frame (point + offsets). Classes unknown to ``objects`` are ignored.
    timings: optional dict to which "voting" and "kabsch" seconds are added. Returns detections by score.
    """
    t0 = time.perf_counter()
    obj_ids = np.asarray(obj_ids)
    keep = keep_mask(obj_ids, confidence, cfg.tau) & np.isin(obj_ids, list(objects.diameters))
    groups = []
    for oid in np.unique(obj_ids[keep]):
        rows = np.flatnonzero(keep & (obj_ids == oid))
        if cfg.mode_radius > 0:
            labels, counts = vote_modes(control_points[rows, 8], np.asarray(confidence, np.float64)[rows],
                                        cfg.mode_radius * objects.diameters[oid], cfg.min_votes)
        else:
            labels, counts = vote_clusters(control_points[rows, 8], cfg.cell)
        for c in np.flatnonzero(counts >= cfg.min_votes):
            groups.append((int(oid), rows[labels == c]))
    t1 = time.perf_counter()
    dets = []
    for oid, members in groups:
        w = np.asarray(confidence, np.float64)[members]
        if cfg.centre_votes:  # the centre only; R is a placeholder (identity) until stage 2 sets it
            c, inl = robust_control_points(control_points[members, 8:9], w, objects.diameters[oid],
                                           cfg.inlier_fraction)
            R = np.eye(3)
            t = c[0] - objects.control_points[oid][8]
            cps = objects.control_points[oid] + t
        else:
            cps, inl = robust_control_points(control_points[members], w, objects.diameters[oid],
                                             cfg.inlier_fraction)
            R, t = kabsch(objects.control_points[oid], cps)
        score = float(w[inl].mean() * inl.mean()) if inl.any() else 0.0
        dets.append(Detection(oid, score, R, t, len(members), cps, members[inl] if inl.any() else members))
    dets = nms(dets, objects.diameters, cfg.nms_fraction, box_centres=objects.box_centres())
    if timings is not None:
        timings["voting"] = timings.get("voting", 0.0) + t1 - t0
        timings["kabsch"] = timings.get("kabsch", 0.0) + time.perf_counter() - t1
    return dets
