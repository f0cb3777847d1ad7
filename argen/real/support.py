"""The support plane of a markerless AR capture: where virtual objects may stand in a real depth frame.

Without a printed board the camera pose is unknown, so each frame's world is the plane the objects stand on:

1. Fit. Valid pixels on a 4-pixel grid within ``plane.centre`` of the image centre are back-projected and
   planes are fitted one after another (RANSAC then least squares, :func:`fit_plane`; each without the
   previous ones' inliers), a point being an inlier within ``inlier_m + inlier_per_m2 * z^2`` (the depth
   noise of a structured-light sensor grows with z^2). Planes whose normal is more than ``max_tilt_deg`` from
   the camera's up axis (-y) are walls, not supports. Of the rest, the one with the most central inliers,
   weighted by their closeness to the image centre, is the support: the dominant horizontal plane near the
   view's centre. No such plane (or too few inliers): the frame is rejected with the reason.
2. Frame. World z is the plane normal (towards the camera side), world x the camera's x axis projected on
   the plane, the origin the centre of the plane's extent on the plane. So placement code written for the
   board (z = 0 is the surface, z up) places on it unchanged.
3. Extent and clearance. Every valid pixel is back-projected into that frame and binned on a grid of
   ``cell`` metres: a cell is *support* where a plane inlier was measured (holes of one cell closed, largest
   connected region kept), and its *clearance* is the height of the lowest real point measured above the
   plane in it (+inf when none). :meth:`Support.fits` accepts an object's pose when every cell under its
   footprint is support (it stands on measured plane: not off the edge, not on space hidden from the camera
   behind something) and no real point lies in or next to its footprint's column below its top plus
   ``clearance``: it neither intersects nor encloses measured real geometry.

Units: metres; K (3, 3) pixels; depth (H, W) float32 metres, 0 = none.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from argen.config import PlaneConfig
from argen.features import backproject
from argen.models.objects import ObjectModel

FIT_STRIDE = 4  # pixels between the points the plane is fitted to
REFITS = 4  # least-squares refits of the support plane (a stable normal: the inliers settle)
CENTRE_SIGMA = 0.25  # width (fraction of the image size) of the weight that favours inliers near the centre


def pixel_rays(rows: np.ndarray, cols: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 3) camera-frame rays with z = 1 of pixels (rows, cols) (N,) int; K: (3, 3)."""
    return np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones(len(rows))], axis=1)


def fit_plane(points: np.ndarray, rng: np.random.Generator, inlier: float | np.ndarray = 0.005,
              iters: int = 200, refits: int = 1) -> tuple[np.ndarray, float, np.ndarray] | None:
    """RANSAC + least-squares plane n.x + c = 0 through (N, 3) metres points; n faces the camera (origin).

    inlier: metres, one distance or one per point (N,). refits: least-squares fits, each to the inliers of the
    one before (the first to RANSAC's). Returns (n (3,), c metres, inliers (N,) bool), or None for fewer than
    3 points or no plane.
    """
    p = np.asarray(points, np.float64)
    if len(p) < 3:
        return None
    tol = np.broadcast_to(np.asarray(inlier, np.float64), (len(p),))
    tri = p[rng.integers(0, len(p), (iters, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12
    if not ok.any():
        return None
    n, tri = n[ok] / norm[ok, None], tri[ok]
    c = -np.einsum("ij,ij->i", n, tri[:, 0])
    counts = (np.abs(p @ n.T + c) < tol[:, None]).sum(axis=0)
    best = int(np.argmax(counts))
    inl = np.abs(p @ n[best] + c[best]) < tol
    for _ in range(refits):
        centroid = p[inl].mean(axis=0)
        normal = np.linalg.svd(p[inl] - centroid, full_matrices=False)[2][-1]
        if normal @ centroid > 0:  # face the camera at the origin
            normal = -normal
        c0 = -float(normal @ centroid)
        inl = np.abs(p @ normal + c0) < tol
        if inl.sum() < 3:
            return None
    return normal, c0, inl


def plane_tolerance(z: np.ndarray, cfg: PlaneConfig) -> np.ndarray:
    """Distance (metres) within which a point at depth z (metres, any shape) lies on the plane."""
    return cfg.inlier_m + cfg.inlier_per_m2 * np.square(z)


@dataclass
class Support:
    """A frame's support plane. T_cam_world: (4, 4) plane frame -> camera (z = normal, origin on the plane).

    support: (Gy, Gx) bool cells of measured plane; clearance: (Gy, Gx) float32 metres, the lowest real point
    above the plane in each cell (inf: none); cell metres; lo: (2,) plane xy (metres) of cell (0, 0)'s corner.
    half_extent: metres, half the side of the square around the origin that holds the support region.
    tilt_deg: the normal's angle to the camera's up axis; inliers: central fit inliers; gap: metres kept
    between an object and real points (PlaneConfig.clearance).
    """

    T_cam_world: np.ndarray
    support: np.ndarray
    clearance: np.ndarray
    cell: float
    lo: np.ndarray
    half_extent: float
    tilt_deg: float
    inliers: int
    gap: float

    def cells(self, footprint: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(under, near) (Gy, Gx) bool cells of a footprint (K, 2) metres: covered, and covered grown by one
        cell plus the gap; None when it reaches beyond the grid."""
        g = (footprint - self.lo) / self.cell  # cell coordinates, cell (i, j) spans [j, j+1) x [i, i+1)
        grow = 1 + int(np.ceil(self.gap / self.cell))
        if g.min() < grow or g[:, 0].max() > self.support.shape[1] - grow or g[:, 1].max() > self.support.shape[0] - grow:
            return None
        under = np.zeros(self.support.shape, np.uint8)
        cv2.fillConvexPoly(under, np.round((g - 0.5) * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
        near = cv2.dilate(under, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))
        return under.astype(bool), near.astype(bool)

    def fits(self, obj: ObjectModel, T_world_obj: np.ndarray, footprint: np.ndarray) -> bool:
        """Whether ``obj`` at ``T_world_obj`` (4, 4) with ``footprint`` (K, 2) stands on measured plane, clear
        of every real point (placement.place_instances' ``fits``)."""
        c = self.cells(footprint)
        if c is None:
            return False
        under, near = c
        if not under.any() or not self.support[under].all():
            return False
        top = float((obj.hull_vertices @ T_world_obj[:3, :3].T + T_world_obj[:3, 3])[:, 2].max())
        return bool((self.clearance[near] > top + self.gap).all())

    def plane_mask(self, depth: np.ndarray, K: np.ndarray, cfg: PlaneConfig) -> np.ndarray:
        """(H, W) bool: the pixels whose measured point lies on this plane (within the plane tolerance)."""
        h = _heights(depth, K, self.T_cam_world)
        return (depth > 0) & (np.abs(h) < plane_tolerance(depth, cfg))

    def info(self) -> dict:
        """What capture_log.json records of the plane: normal (camera frame), camera height above it, tilt,
        central inliers and the support area (m^2)."""
        return {"normal": [round(float(v), 6) for v in self.T_cam_world[:3, 2]],
                "camera_height_m": round(float(-self.T_cam_world[:3, 2] @ self.T_cam_world[:3, 3]), 6),
                "tilt_deg": round(self.tilt_deg, 4), "inliers": self.inliers,
                "area_m2": round(float(self.support.sum()) * self.cell ** 2, 4)}


def _heights(depth: np.ndarray, K: np.ndarray, T_cam_world: np.ndarray) -> np.ndarray:
    """(H, W) height (metres) of each pixel's measured point above the plane z = 0 of T_cam_world (nan: none)."""
    rows, cols = np.indices(depth.shape)
    p = backproject(rows.ravel(), cols.ravel(), depth.ravel().astype(np.float64), K)
    h = (p - T_cam_world[:3, 3]) @ T_cam_world[:3, 2]
    return np.where(depth.ravel() > 0, h, np.nan).reshape(depth.shape)


def find_support(depth: np.ndarray, K: np.ndarray, cfg: PlaneConfig, rng: np.random.Generator) -> Support | str:
    """The frame's support plane (see the module docstring), or the reason there is none (one line)."""
    H, W = depth.shape
    rows, cols = np.mgrid[FIT_STRIDE // 2:H:FIT_STRIDE, FIT_STRIDE // 2:W:FIT_STRIDE]
    rows, cols = rows.ravel(), cols.ravel()
    du, dv = (cols - (W - 1) / 2) / W, (rows - (H - 1) / 2) / H
    keep = (depth[rows, cols] > 0) & (np.abs(du) <= cfg.centre) & (np.abs(dv) <= cfg.centre)
    if keep.sum() < cfg.min_inliers:
        return f"no usable plane (only {int(keep.sum())} valid depth points near the centre)"
    z = depth[rows[keep], cols[keep]].astype(np.float64)
    pts = backproject(rows[keep], cols[keep], z, K)
    tol = plane_tolerance(z, cfg)
    weight = np.exp(-(du[keep] ** 2 + dv[keep] ** 2) / (2 * CENTRE_SIGMA ** 2))
    left = np.ones(len(pts), bool)
    best, tilts = None, []
    for _ in range(cfg.candidates):
        if left.sum() < cfg.min_inliers:
            break
        fit = fit_plane(pts[left], rng, tol[left], refits=REFITS)
        if fit is None:
            break
        n, c, inl = fit
        idx = np.flatnonzero(left)[inl]
        left[idx] = False
        tilt = float(np.degrees(np.arccos(np.clip(-n[1], -1.0, 1.0))))
        tilts.append(round(tilt, 1))
        if len(idx) < cfg.min_inliers or tilt > cfg.max_tilt_deg:
            continue
        score = float(weight[idx].sum())
        if best is None or score > best[0]:
            best = (score, n, c, len(idx), tilt)
    if best is None:
        return (f"no usable plane (no plane of at least {cfg.min_inliers} points within {cfg.max_tilt_deg:g} deg "
                f"of horizontal near the centre; tilts found: {tilts})")
    _, n, c, count, tilt = best
    T = _plane_frame(n, -c * n)
    return _extent(depth, K, T, cfg, tilt, count)


def _plane_frame(n: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(4, 4) plane -> camera: z = n (3,), x = the camera x axis projected on the plane, origin (3,) metres."""
    x = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(x) < 1e-6:  # the plane is seen edge-on along x: any x in the plane
        x = np.cross(n, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(n, x), n], axis=1)
    T[:3, 3] = origin
    return T


def _extent(depth: np.ndarray, K: np.ndarray, T: np.ndarray, cfg: PlaneConfig, tilt: float, count: int) -> Support | str:
    """Support and clearance grids of the plane T (4, 4) from every valid pixel, and the frame re-centred on
    the largest support region."""
    valid = depth > 0
    rows, cols = np.nonzero(valid)
    z = depth[valid].astype(np.float64)
    q = (backproject(rows, cols, z, K) - T[:3, 3]) @ T[:3, :3]  # plane coordinates
    tol = plane_tolerance(z, cfg)
    on = np.abs(q[:, 2]) < tol
    above = q[:, 2] >= tol
    lo = np.floor(q[on, :2].min(axis=0) / cfg.cell) * cfg.cell - 4 * cfg.cell
    hi = q[on, :2].max(axis=0) + 4 * cfg.cell
    shape = tuple(int(v) for v in np.ceil((hi - lo) / cfg.cell)[::-1])  # (Gy, Gx)
    ij = np.floor((q[:, :2] - lo) / cfg.cell).astype(np.int64)[:, ::-1]  # (row = y, col = x)
    inside = (ij >= 0).all(axis=1) & (ij[:, 0] < shape[0]) & (ij[:, 1] < shape[1])
    sup = np.zeros(shape, np.uint8)
    sup[tuple(ij[on & inside].T)] = 1
    sup = cv2.morphologyEx(sup, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    n_comp, labels, stats, _ = cv2.connectedComponentsWithStats(sup, connectivity=4)
    if n_comp < 2:
        return "no usable plane (no measured extent)"
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    sup = labels == biggest
    clear = np.full(shape, np.inf, np.float32)
    sel = above & inside
    np.minimum.at(clear, tuple(ij[sel].T), q[sel, 2].astype(np.float32))
    # re-centre the frame on the support region's bounding box (the placement square is centred on the origin)
    ys, xs = np.nonzero(sup)
    a = lo + cfg.cell * np.array([xs.min(), ys.min()])
    b = lo + cfg.cell * np.array([xs.max() + 1, ys.max() + 1])
    mid = (a + b) / 2
    T = T.copy()
    T[:3, 3] += T[:3, :2] @ mid
    return Support(T, sup, clear, cfg.cell, lo - mid, float((b - a).max() / 2), tilt, int(count), cfg.clearance)
