"""The frame's dominant plane (the desk or the board the objects stand on), so that stage 1 can sample fewer of its
points: a plane is most of a tabletop frame (about 80 % of the points of a simulated LineMOD frame, 57 % of a real
ycbv_real one) and carries no object, so the 4096 points stage 1 sees, and the 1024 keypoints it predicts at, land
more often on the objects. The plane is found by RANSAC over 3-point planes drawn from the caller's generator, then
refitted to its points by least squares. Not open3d's ``segment_plane``: it draws its samples on several threads,
so the same frame and seed gave different planes from one call to the next, and training items and predictions
must repeat exactly."""

from __future__ import annotations

import numpy as np

#: Distance to the plane, metres, within which a point is the plane's: the board's magazines and a Kinect's depth
#: noise at 1.5 m (about 6 mm) stay within it.
PLANE_DISTANCE = 0.01
#: A plane holding fewer of the frame's points is not dropped (a frame without a large support surface, or one
#: filled by an object's face).
MIN_PLANE_SHARE = 0.2
#: RANSAC hypotheses, and the points they are scored on (a random subset: the plane is then measured on all).
PLANE_ITERATIONS = 200
PLANE_FIT_POINTS = 1024


def dominant_plane(xyz: np.ndarray, rng: np.random.Generator, distance: float = PLANE_DISTANCE,
                   min_share: float = MIN_PLANE_SHARE) -> np.ndarray:
    """Which points lie on the frame's largest plane.

    xyz: (N,3) metres (camera frame); rng: draws the fitted subset and the hypotheses. Returns (N,) bool: the points
    within ``distance`` of the plane that RANSAC fits to a random subset of :data:`PLANE_FIT_POINTS` points; all
    False when that plane holds less than ``min_share`` of the points or the frame has too few points to fit one.
    """
    xyz = np.asarray(xyz, np.float64)
    n = len(xyz)
    none = np.zeros(n, bool)
    if n < 3:
        return none
    fit = xyz if n <= PLANE_FIT_POINTS else xyz[rng.choice(n, PLANE_FIT_POINTS, replace=False)]
    p = fit[rng.integers(0, len(fit), (PLANE_ITERATIONS, 3))]  # (H,3,3) three points a hypothesis
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    length = np.linalg.norm(normals, axis=1)
    ok = length > 1e-9  # not three points on a line
    if not ok.any():
        return none
    normals = normals[ok] / length[ok, None]
    offsets = -np.einsum("hk,hk->h", normals, p[ok, 0])
    # einsum, not matmul: a BLAS call leaves OpenBLAS's threads spinning beside torch's, which then ran the
    # stage-1 network four times slower on 2 cores (measured: 70 against 18 ms a frame)
    inliers = np.abs(np.einsum("nk,hk->nh", fit, normals) + offsets) <= distance  # (n_fit, H)
    best = fit[inliers[:, int(np.argmax(inliers.sum(axis=0)))]]
    centre = best.mean(axis=0)  # least-squares plane through the best hypothesis's points
    spread = np.einsum("nj,nk->jk", best - centre, best - centre)
    normal = np.linalg.eigh(spread)[1][:, 0]  # the direction of least spread
    on = np.abs(np.einsum("nk,k->n", xyz - centre, normal)) <= distance
    return on if on.mean() >= min_share else none


def thin_plane_rows(xyz: np.ndarray, num_points: int, keep: float, rng: np.random.Generator) -> np.ndarray:
    """The rows stage 1 may sample from when it keeps only a ``keep`` share of the dominant plane's points
    (:func:`dominant_plane`): every point off the plane and a random ``keep`` share of those on it, but never fewer
    rows than ``num_points`` while the frame has them (more plane points fill up to that).

    xyz: (N,3) metres; keep: in [0, 1], 1 returns every row. Returns (M,) int64 sorted rows of ``xyz``.
    """
    n = len(xyz)
    if keep >= 1.0:
        return np.arange(n, dtype=np.int64)
    on = dominant_plane(xyz, rng)
    plane, off = np.flatnonzero(on), np.flatnonzero(~on)
    take = min(len(plane), max(int(round(keep * len(plane))), num_points - len(off)))
    kept = rng.choice(plane, take, replace=False) if take > 0 else plane[:0]
    return np.sort(np.concatenate([off, kept])).astype(np.int64)
