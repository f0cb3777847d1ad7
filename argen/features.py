"""Frame -> points: the per-point features ``argen label`` stores and ``detector predict`` computes alike.

A depth image (metres, 0 = missing) and its intrinsics K become camera-frame points (OpenCV axes) in pixel order:
back-projection (``X = (col - cx) Z / fx``, ``Y = (row - cy) Z / fy``), an optional one-point-per-voxel thinning
and a seeded uniform subsample, normals from the depth grid (see :func:`grid_normals`) and colours RGB / 255.
The feature row is ``[X, Y, Z metres, R, G, B in [0, 1], Nx, Ny, Nz]``. :func:`project` is the inverse (points to
pixels), with :data:`BOX_EDGES` and :func:`palette` the drawing aids that ``argen preview`` and ``detector
predict`` share. Pure numpy and OpenCV; no file formats here (``argen.bop`` reads the images).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from argen.errors import ArgenError

NORMAL_STEP = 2  # pixels between a point and the neighbours its tangents use
JUMP_REL = 0.03  # a neighbour whose depth differs by more than this fraction of the depth is across an edge
#: The 12 edges of a box between its 8 control-point corners, which come in ``itertools.product((x0, x1), (y0, y1),
#: (z0, z1))`` order: corners k and k ^ b (b = 1, 2, 4) differ along one axis.
BOX_EDGES = [(k, k ^ b) for k in range(8) for b in (1, 2, 4) if k < k ^ b]


def backproject(rows: np.ndarray, cols: np.ndarray, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points of pixels. rows, cols: (N,) int; z: (N,) metres; K: (3,3). Returns (N,3) float64."""
    x = (cols - K[0, 2]) * z / K[0, 0]
    y = (rows - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], axis=1)


def subsample(n: int, points: np.ndarray | None, max_points: int, voxel: float,
              rng: np.random.Generator) -> np.ndarray:
    """Indices (sorted) of at most ``max_points`` of ``n`` points: one per voxel (if voxel > 0), then uniform random.

    points: (n,3) metres in pixel order (needed only when voxel > 0). Returns (k,) int64 into the n points.
    """
    keep = np.arange(n)
    if n <= max_points:
        return keep
    if voxel > 0:
        v = np.floor(points / voxel).astype(np.int64)
        v -= v.min(axis=0)
        dims = v.max(axis=0) + 1
        key = (v[:, 0] * dims[1] + v[:, 1]) * dims[2] + v[:, 2]
        _, keep = np.unique(key, return_index=True)
        keep.sort()
    if len(keep) > max_points:
        keep = np.sort(keep[rng.choice(len(keep), max_points, replace=False)])
    return keep


def smooth_depth(depth: np.ndarray) -> np.ndarray:
    """Edge-preserving smoothing for normals. depth: (H,W) float32 metres, 0 = missing (stays 0)."""
    out = cv2.bilateralFilter(depth, 5, 0.01, 2.0)
    out[depth <= 0] = 0
    return out


def grid_normals(depth: np.ndarray, K: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                 step: int = NORMAL_STEP, jump: float = JUMP_REL) -> np.ndarray:
    """Unit normals at pixels from the (smoothed) depth grid, oriented toward the camera.

    depth: (H,W) float32 metres, 0 = missing; K: (3,3); rows, cols: (N,) int pixels with depth > 0.
    Returns (N,3) float32. See the module docstring for the method.
    """
    h, w = depth.shape
    z = depth[rows, cols].astype(np.float64)
    p = backproject(rows, cols, z, K)

    def tangent(dr: int, dc: int) -> tuple[np.ndarray, np.ndarray]:
        sides, oks = [], []
        for s in (step, -step):
            r2, c2 = np.clip(rows + s * dr, 0, h - 1), np.clip(cols + s * dc, 0, w - 1)
            z2 = depth[r2, c2].astype(np.float64)
            ok = (z2 > 0) & (np.abs(z2 - z) <= jump * z) & ((r2 != rows) | (c2 != cols))
            sides.append((backproject(r2, c2, z2, K) - p) * (1 if s > 0 else -1))
            oks.append(ok)
        (f, b), (okf, okb) = sides, oks
        t = np.where(okf[:, None], f, 0) + np.where(okb[:, None], b, 0)
        return t, okf | okb

    tu, oku = tangent(0, 1)
    tv, okv = tangent(1, 0)
    n = np.cross(tu, tv)
    norm = np.linalg.norm(n, axis=1)
    good = oku & okv & (norm > 1e-12)
    toward = -p / np.linalg.norm(p, axis=1, keepdims=True)
    n = np.where(good[:, None], n / np.where(good, norm, 1)[:, None], toward)
    n *= np.where(np.einsum("ij,ij->i", n, p) > 0, -1.0, 1.0)[:, None]
    return n.astype(np.float32)


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel (x, y) of camera-frame points. points: (..., 3) metres; K: (3,3). Returns (..., 2) float64."""
    p = np.asarray(points, np.float64)
    z = np.where(p[..., 2:3] > 1e-6, p[..., 2:3], 1e-6)
    return np.stack([K[0, 0] * p[..., 0] / z[..., 0] + K[0, 2], K[1, 1] * p[..., 1] / z[..., 0] + K[1, 2]], axis=-1)


def palette(n: int) -> np.ndarray:
    """(n,3) uint8 distinct, saturated RGB colours (golden-ratio hues)."""
    hues = (np.arange(n) * 0.618034 % 1.0 * 180).astype(np.uint8)
    hsv = np.stack([hues, np.full(n, 230, np.uint8), np.full(n, 255, np.uint8)], axis=1)[None]
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0]


@dataclass
class FramePoints:
    """A frame's points. features: (N,9) float32 (see the module docstring); rows, cols: (N,) int64 pixel of each
    point, in pixel order; flat: (N,) int64 ``row * W + col``."""

    features: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    flat: np.ndarray


def check_max_depth(max_depth: float) -> float:
    """A working volume's depth (metres along z, :func:`frame_points`' ``max_depth``), checked: positive, and at
    most 50 (more is millimetres given as metres). Returns it as a float; ArgenError otherwise."""
    if not max_depth > 0:
        raise ArgenError(f"--max-depth must be positive (metres), got {max_depth}")
    if max_depth > 50:
        raise ArgenError(f"--max-depth is metres: {max_depth} is too far (did you give millimetres?)")
    return float(max_depth)


def frame_points(depth: np.ndarray, K: np.ndarray, rgb: np.ndarray | None, max_points: int, voxel: float,
                 rng: np.random.Generator, max_depth: float | None = None) -> FramePoints:
    """The points of a depth image: pixels with depth in (0, ``max_depth``], thinned (:func:`subsample`) to at
    most ``max_points``, with colours and grid normals.

    depth: (H,W) float32 metres, 0 = missing; K: (3,3); rgb: (H,W,3) uint8 or None (colours 0); voxel: metres
    (0 = off); rng: the subsampling generator; max_depth: metres or None (no limit).
    """
    h, w = depth.shape
    valid = (depth > 0) & (depth <= (np.inf if max_depth is None else max_depth))
    flat = np.flatnonzero(valid)
    rows, cols = flat // w, flat % w
    voxelise = voxel > 0 and len(flat) > max_points
    pts = backproject(rows, cols, depth.reshape(-1)[flat].astype(np.float64), K) if voxelise else None
    keep = subsample(len(flat), pts, max_points, voxel, rng)
    flat, rows, cols = flat[keep], rows[keep], cols[keep]
    pts = backproject(rows, cols, depth.reshape(-1)[flat].astype(np.float64), K)
    normals = grid_normals(smooth_depth(depth), K, rows, cols)
    colour = (rgb.reshape(-1, 3)[flat].astype(np.float32) / 255.0) if rgb is not None \
        else np.zeros((len(flat), 3), np.float32)
    return FramePoints(np.concatenate([pts.astype(np.float32), colour, normals], axis=1), rows, cols, flat)
