"""How real a dataset's depth is: its distance to the ground-truth surfaces, holes and depth steps.

The same measure works on argen's captures and on real BOP test sets (LineMOD's Kinect frames with their own
ground truth), so simulated and real depth can be compared side by side (``bench/bench_noise.py``): for every
visible ground-truth instance, back-project its visible-mask pixels with measured depth, move them into the
model frame with the ground-truth pose, and take their distances to the model surface (exact point-to-triangle
distances, open3d). Those distances carry the sensor's error and, on real data, the ground truth's own error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from argen import bop
from argen.features import backproject
from argen.models.objects import ObjectModel, surface_scene

#: Distance bins of the benchmark, metres (the camera-to-point depth z).
DISTANCE_BINS = ((0.6, 0.8), (0.8, 0.95), (0.95, 1.1))
#: Incidence-angle bins, degrees (angle between the viewing ray and the model surface's normal).
ANGLE_BINS = ((0, 30), (30, 60), (60, 90))


@dataclass
class SurfaceErrors:
    """Per measured pixel of the visible instances: dist (N,) metres to the model surface, z (N,) metres,
    angle (N,) degrees of incidence; and per frame the share of pixels with no depth."""

    dist: np.ndarray
    z: np.ndarray
    angle: np.ndarray
    invalid_fraction: list[float]

    @staticmethod
    def concat(parts: list["SurfaceErrors"]) -> "SurfaceErrors":
        return SurfaceErrors(np.concatenate([p.dist for p in parts]) if parts else np.zeros(0),
                             np.concatenate([p.z for p in parts]) if parts else np.zeros(0),
                             np.concatenate([p.angle for p in parts]) if parts else np.zeros(0),
                             [f for p in parts for f in p.invalid_fraction])


class _Surfaces:
    """Raycasting scenes of the models, built once per object."""

    def __init__(self, models: dict[int, ObjectModel]):
        self.models = models
        self._scenes: dict[int, o3d.t.geometry.RaycastingScene] = {}

    def scene(self, obj_id: int) -> o3d.t.geometry.RaycastingScene:
        if obj_id not in self._scenes:
            self._scenes[obj_id] = surface_scene(self.models[obj_id].mesh)
        return self._scenes[obj_id]


def frame_errors(scene: bop.BopScene, im_id: int, surfaces: _Surfaces, min_visib: float = 0.1) -> SurfaceErrors:
    """:class:`SurfaceErrors` of one frame's instances at least ``min_visib`` visible (BOP19's rule)."""
    depth = scene.read_depth(im_id)
    K = scene.cameras[im_id].K
    infos = scene.gt_infos.get(im_id, [])
    dist, zs, angles = [], [], []
    for k, g in enumerate(scene.gts[im_id]):
        if g.obj_id not in surfaces.models:
            continue
        if k < len(infos) and float(infos[k].get("visib_fract", 1.0)) < min_visib:
            continue
        mask = scene.read_mask(im_id, k, visib=True)
        if mask is None:
            continue
        rows, cols = np.nonzero(mask & (depth > 0))
        if len(rows) == 0:
            continue
        z = depth[rows, cols].astype(np.float64)
        p = backproject(rows, cols, z, K)
        q = (p - g.t) @ g.R  # model frame: R^T (p - t)
        ans = surfaces.scene(g.obj_id).compute_closest_points(o3d.core.Tensor(q.astype(np.float32)))
        closest = ans["points"].numpy().astype(np.float64)
        normal = ans["primitive_normals"].numpy().astype(np.float64)
        ray = -(g.R.T @ p.T).T  # towards the camera, model frame
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        cos = np.abs(np.einsum("ij,ij->i", normal, ray))
        dist.append(np.linalg.norm(q - closest, axis=1))
        zs.append(z)
        angles.append(np.degrees(np.arccos(np.clip(cos, 0, 1))))
    cat = (lambda a: np.concatenate(a) if a else np.zeros(0))  # noqa: E731
    return SurfaceErrors(cat(dist), cat(zs), cat(angles), [float((depth <= 0).mean())])


def dataset_errors(root, split: str, models: dict[int, ObjectModel], max_frames: int | None = None) -> SurfaceErrors:
    """:func:`frame_errors` over (the first ``max_frames`` of) every scene of ``root/split``."""
    surfaces = _Surfaces(models)
    parts = []
    for sid in bop.list_scenes(root, split):
        sc = bop.load_scene(root, split, sid)
        for im in sc.im_ids:
            if max_frames is not None and len(parts) >= max_frames:
                break
            parts.append(frame_errors(sc, im, surfaces))
    return SurfaceErrors.concat(parts)


def summary(err: SurfaceErrors, mask: np.ndarray | None = None) -> dict:
    """{n, median_mm, p95_mm} of the distances (where ``mask``)."""
    d = err.dist if mask is None else err.dist[mask]
    if len(d) == 0:
        return {"n": 0, "median_mm": float("nan"), "p95_mm": float("nan")}
    return {"n": int(len(d)), "median_mm": float(np.median(d) * 1000), "p95_mm": float(np.percentile(d, 95) * 1000)}


def depth_steps(root, split: str, lo: float = 0.95, hi: float = 1.05, max_frames: int | None = None) -> dict:
    """Quantisation: the distinct depth values in [lo, hi] metres over the frames and the median step between
    neighbouring ones (mm). A disparity sensor has a few dozen levels there; a ToF one has as many as its units."""
    values = set()
    n = 0
    for sid in bop.list_scenes(root, split):
        sc = bop.load_scene(root, split, sid)
        for im in sc.im_ids:
            if max_frames is not None and n >= max_frames:
                break
            d = sc.read_depth(im)
            sel = d[(d >= lo) & (d <= hi)]
            values.update(np.round(sel * 1e5).astype(np.int64).tolist())  # 0.01 mm bins
            n += 1
    v = np.array(sorted(values), float) / 1e2  # mm
    step = float(np.median(np.diff(v))) if len(v) > 1 else float("nan")
    return {"distinct": int(len(v)), "median_step_mm": step}
