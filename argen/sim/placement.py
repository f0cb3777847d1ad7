"""Random placement of objects on the board's free area, in stable resting poses, without overlap.

World frame = board frame: origin at the board centre on its top surface, z up (board normal).
Objects stand on z = 0 in one of their most likely resting poses, rotated by a random yaw about z.
Two footprints (2D convex hulls on the board plane) must be at least ``min_gap`` apart; a candidate
that overlaps is rejected and resampled, at most ``max_tries`` times per instance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from argen.config import PlacementConfig
from argen.models.objects import ObjectModel


@dataclass
class Placement:
    """One placed instance. T_world_obj: (4,4), metres; footprint: (K,2) convex polygon, metres."""

    obj: ObjectModel
    T_world_obj: np.ndarray
    footprint: np.ndarray


def convex_hull_2d(points: np.ndarray) -> np.ndarray:
    """(K,2) counter-clockwise convex hull of (N,2) points (metres)."""
    hull = cv2.convexHull(points.astype(np.float32), clockwise=False, returnPoints=True)
    return hull.reshape(-1, 2).astype(np.float64)


def separation(a: np.ndarray, b: np.ndarray) -> float:
    """Separating-axis gap between convex polygons a (K,2) and b (L,2), metres.

    Positive: the largest gap between their projections over all edge normals (a lower bound of
    their true distance, so ``separation >= gap`` guarantees the polygons are at least ``gap`` apart).
    Zero or negative: they overlap.
    """
    best = -np.inf
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)
        norm = np.linalg.norm(normals, axis=1)
        normals = normals[norm > 1e-12] / norm[norm > 1e-12, None]
        pa, pb = a @ normals.T, b @ normals.T  # (K,E), (L,E)
        gap = np.maximum(pb.min(0) - pa.max(0), pa.min(0) - pb.max(0))
        best = max(best, float(gap.max(initial=-np.inf)))
    return best


def beside(other: np.ndarray, footprint: np.ndarray, direction: np.ndarray, gap: float) -> np.ndarray:
    """(2,) shift that puts ``footprint`` next to ``other`` along ``direction``, ``gap`` metres apart.

    other, footprint: (K,2), (L,2) convex polygons, metres; direction: (2,) unit vector from ``other``'s centroid.
    After the shift their projections on ``direction`` are exactly ``gap`` apart, so for gap > 0 they do not
    overlap; ``footprint`` is centred on ``other``'s centroid line along ``direction``.
    """
    c = other.mean(axis=0)
    reach = (other @ direction).max() - c @ direction - (footprint @ direction).min() + gap
    return c + direction * reach - footprint.mean(axis=0) + (footprint.mean(axis=0) @ direction) * direction


def resting_transform(obj: ObjectModel, pose_index: int, n_poses: int) -> np.ndarray:
    """(4,4) transform that puts ``obj`` in its resting pose: lowest point at z=0, footprint centred."""
    key = ("rest", pose_index, n_poses)
    if key not in obj._cache:
        T_stable, _ = obj.stable_poses(n_poses)
        T = T_stable[pose_index].copy()
        v = obj.hull_vertices @ T[:3, :3].T + T[:3, 3]
        hull = convex_hull_2d(v[:, :2])
        T[:3, 3] -= np.array([*(hull.min(0) + hull.max(0)) / 2, v[:, 2].min()])
        obj._cache[key] = T
    return obj._cache[key].copy()


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.eye(4)
    R[:2, :2] = [[c, -s], [s, c]]
    return R


def footprint_of(obj: ObjectModel, T_world_obj: np.ndarray) -> np.ndarray:
    """(K,2) convex footprint of ``obj`` under ``T_world_obj`` on the board plane, metres."""
    v = obj.hull_vertices @ T_world_obj[:3, :3].T + T_world_obj[:3, 3]
    return convex_hull_2d(v[:, :2])


def pose_weights(probs: np.ndarray, uniform: float) -> np.ndarray:
    """(P,) probabilities of drawing each resting pose: the physical ones ``probs`` (P,) mixed with a uniform
    share ``uniform`` in [0, 1] (0: physics only; 1: every pose alike)."""
    probs = np.asarray(probs, np.float64)
    w = (1.0 - uniform) * probs / probs.sum() + uniform / len(probs)
    return w / w.sum()


def choose_instances(objects: list[ObjectModel], cfg: PlacementConfig, rng: np.random.Generator) -> list[ObjectModel]:
    """Draw which objects (and how many copies of each) go into one frame."""
    lo, hi = cfg.objects_per_frame
    k = min(int(rng.integers(lo, hi + 1)), len(objects))
    picked = rng.choice(len(objects), size=k, replace=False)
    out = []
    for i in picked:
        n = int(rng.integers(cfg.instances_per_object[0], cfg.instances_per_object[1] + 1))
        out.extend([objects[int(i)]] * n)
    return out


def place_instances(
    instances: list[ObjectModel],
    cfg: PlacementConfig,
    half_extent: float,
    rng: np.random.Generator,
    obstacles: list[np.ndarray] | None = None,
    fits: Callable[[ObjectModel, np.ndarray, np.ndarray], bool] | None = None,
) -> tuple[list[Placement], list[ObjectModel]]:
    """Place each instance inside the square [-half_extent, half_extent]^2 without overlaps.

    obstacles: footprints (K,2) already on the board. fits(obj, T_world_obj (4,4), footprint (K,2)) -> whether
    a candidate that passed the other checks may stand there (the real geometry of a markerless capture,
    argen.real.support); None: every candidate may. Returns the placements and the instances that could not be
    placed within ``cfg.max_tries`` attempts each.
    """
    placed: list[Placement] = []
    failed: list[ObjectModel] = []
    taken = list(obstacles or [])
    for obj in instances:
        _, probs = obj.stable_poses(cfg.stable_poses)
        probs = pose_weights(probs, cfg.uniform_poses)
        ok = False
        for _ in range(cfg.max_tries):
            pose_idx = int(rng.choice(len(probs), p=probs))
            T_rest = resting_transform(obj, pose_idx, cfg.stable_poses)
            yaw = rng.uniform(0.0, 2 * np.pi)
            T = _rz(yaw) @ T_rest
            if placed and rng.random() < cfg.beside:
                a = rng.uniform(0.0, 2 * np.pi)
                other = placed[int(rng.integers(len(placed)))].footprint
                xy = beside(other, footprint_of(obj, T), np.array([np.cos(a), np.sin(a)]),
                            cfg.min_gap + 0.001 + rng.uniform(0.0, 0.02))
            else:
                xy = rng.uniform(-half_extent, half_extent, size=2)
            T[:2, 3] += xy
            fp = footprint_of(obj, T)
            if fp.min() < -half_extent or fp.max() > half_extent:
                continue
            if any(separation(fp, other) < cfg.min_gap for other in taken):
                continue
            if fits is not None and not fits(obj, T, fp):
                continue
            placed.append(Placement(obj, T, fp))
            taken.append(fp)
            ok = True
            break
        if not ok:
            failed.append(obj)
    return placed, failed


def never_fit(objects: list[ObjectModel], cfg: PlacementConfig, half_extent: float, yaws: int = 36) -> list[str]:
    """Descriptions of the objects that cannot stand inside [-half_extent, half_extent]^2 in any resting pose.

    Tries every resting pose with ``yaws`` rotations about the board normal; an object listed here would
    fail every placement attempt, so capture refuses to start instead of writing frames without it.
    """
    bad = []
    for obj in objects:
        _, probs = obj.stable_poses(cfg.stable_poses)
        best = np.inf
        for pose_idx in range(len(probs)):
            T_rest = resting_transform(obj, pose_idx, cfg.stable_poses)
            for yaw in np.linspace(0.0, np.pi / 2, yaws, endpoint=False):
                fp = footprint_of(obj, _rz(yaw) @ T_rest)
                best = min(best, float((fp.max(axis=0) - fp.min(axis=0)).max()))
        if best > 2 * half_extent:
            bad.append(f"'{obj.name}' ({best:.3f} m wide at best)")
    return bad
