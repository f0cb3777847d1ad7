"""Pose verification against the frame's depth: does the sensor agree with a detection's pose? A detection's support
(the share of its own points on the model surface) cannot see a model that is too big for them, or placed on the
wrong thing: a box posed on a smaller brick explains every brick point. The frame's depth can: along the rays of
such a pose's model points the sensor saw the table behind (:func:`depth_consistency`). Nor can it see a model posed
on part of something larger, a box on a keyboard's edge: every model point is seen, but the keyboard's surfaces run
on past the box's outline in the planes of its faces, where a real box's surfaces end (:func:`surface_continuation`).
Numpy; metres; poses map model into camera points (``x_cam = R @ x_model + t``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import minimum_filter
from scipy.spatial import cKDTree

from detector.geometry.icp import support_radius


@dataclass
class RangeImage:
    """The frame's point cloud binned by viewing direction: for each cell of the normalised image plane
    (x/z, y/z) the depth of the nearest point in it. cell: cell size in normalised coordinates (about radians);
    origin: (2,) normalised coordinates of cell (0, 0)'s corner; z: (H,W) float64 metres, inf = no point;
    near: (H,W) the nearest depth in each cell and its 8 neighbours."""

    cell: float
    origin: np.ndarray
    z: np.ndarray
    near: np.ndarray | None = None

    def lookup(self, points: np.ndarray, around: bool = False) -> np.ndarray:
        """Depth (metres) of the nearest frame point along each point's ray (``around``: in its cell or the 8 cells
        around it): points (N,3) camera frame, metres. Returns (N,) float64, inf where the cell is empty, off the
        image or the point is behind the camera."""
        p = np.asarray(points, np.float64)
        z = p[:, 2]
        ok = z > 1e-6
        uv = np.zeros((len(p), 2))
        uv[ok] = p[ok, :2] / z[ok, None]
        ij = np.floor((uv - self.origin) / self.cell).astype(np.int64)
        h, w = self.z.shape
        ok &= (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        out = np.full(len(p), np.inf)
        out[ok] = (self.near if around else self.z)[ij[ok, 1], ij[ok, 0]]
        return out


def range_image(cloud: np.ndarray, per_cell: float = 1.5, grid: int = 64) -> RangeImage:
    """Bin a frame's cloud (M,3) camera frame, metres (a subsampled depth image) by viewing direction.

    The cell is sized so that it holds ``per_cell`` points on average where the cloud has points (the area they
    cover is counted on a ``grid`` x ``grid`` raster of their extent), so most cells hold a point whatever the
    sensor's resolution and the cloud's subsampling. An empty cloud gives an image with no cells.
    """
    p = np.asarray(cloud, np.float64)
    p = p[p[:, 2] > 1e-6] if len(p) else p.reshape(0, 3)
    if len(p) < 2:
        return RangeImage(1.0, np.zeros(2), np.full((0, 0), np.inf), np.full((0, 0), np.inf))
    uv = p[:, :2] / p[:, 2:3]
    origin = uv.min(axis=0)
    extent = np.maximum(uv.max(axis=0) - origin, 1e-9)
    coarse = np.minimum((uv - origin) / extent * grid, grid - 1).astype(np.int64)
    covered = np.count_nonzero(np.bincount(coarse[:, 1] * grid + coarse[:, 0], minlength=grid * grid)) * \
        float(np.prod(extent)) / grid ** 2
    cell = float(np.sqrt(per_cell * covered / len(p)))
    ij = np.floor((uv - origin) / cell).astype(np.int64)
    w, h = ij.max(axis=0) + 1
    z = np.full(h * w, np.inf)
    np.minimum.at(z, ij[:, 1] * w + ij[:, 0], p[:, 2])
    z = z.reshape(h, w)
    return RangeImage(cell, origin, z, minimum_filter(z, size=3, mode="constant", cval=np.inf))


def depth_consistency(ri: RangeImage, model_points: np.ndarray, R: np.ndarray, t: np.ndarray, tolerance: float,
                      free_space: float) -> np.ndarray:
    """How far the frame's depth agrees with the model under each pose: seen / (seen + seen through).

    model_points: (P,3) model frame, metres; R (K,3,3), t (K,3) K poses; tolerance: metres, a model point whose
    ray meets a frame point within this depth is seen; free_space: metres, a model point whose ray's nearest frame
    point, and those of the rays next to it, lie more than this behind it is seen through: the sensor saw past where
    the model claims a surface (a pose of the wrong size or shape, or on the wrong thing); the rays next to it keep
    a model edge that falls a cell off the object's outline from counting. Points behind a nearer frame point
    (occluded, or the model's own far side) and on empty rays count for neither. Returns (K,) float64 in [0, 1], 0 where no point
    is either.
    """
    seen, through = depth_votes(ri, model_points, R, t, tolerance, free_space)
    return np.where(seen + through > 0, seen / np.maximum(seen + through, 1), 0.0)


def depth_votes(ri: RangeImage, model_points: np.ndarray, R: np.ndarray, t: np.ndarray, tolerance: float,
                free_space: float) -> tuple[np.ndarray, np.ndarray]:
    """For each of K poses, how many model points (P,3) the frame sees and how many it sees through (as
    :func:`depth_consistency` defines them). R (K,3,3), t (K,3) metres. Returns two (K,) int64."""
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
    x = np.einsum("kij,pj->kpi", R, np.asarray(model_points, np.float64)) + t[:, None]  # (K,P,3)
    flat = x.reshape(-1, 3)
    zs, around = ri.lookup(flat).reshape(x.shape[:2]), ri.lookup(flat, around=True).reshape(x.shape[:2])
    zm = x[..., 2]
    seen = (np.isfinite(zs) & (np.abs(zs - zm) <= tolerance)).sum(axis=1)
    through = (np.isfinite(around) & (around > zm + free_space)).sum(axis=1)
    return seen, through


def pose_consistency(frame: RangeImage, objects, cfg, obj_id: int, R: np.ndarray, t: np.ndarray,
                     max_points: int | None = None) -> np.ndarray:
    """:func:`depth_consistency` of K poses of object ``obj_id``, R (K,3,3), t (K,3) metres, with the depth check's
    tolerances: ``cfg.depth_tolerance`` times the support distance (:func:`detector.geometry.icp.support_radius` of
    ``cfg``, a :class:`detector.geometry.types.GeometryConfig`), the free-space margin twice that. objects: the
    :class:`detector.geometry.types.ObjectInfo`; max_points: measure on at most about this many of its model points
    (every k-th; None: all). Returns (K,) float64 in [0, 1]."""
    tol = cfg.depth_tolerance * support_radius(cfg.support_distance, cfg.support_floor, objects.diameters[obj_id])
    pts = objects.model_points[obj_id]
    if max_points is not None and len(pts) > max_points:
        pts = pts[::-(-len(pts) // max_points)]
    return depth_consistency(frame, pts, R, t, tol, 2 * tol)


def depth_checked(detections: list, frame: RangeImage, objects, cfg, refined: bool = False) -> list:
    """Copies of ``detections`` (:class:`detector.geometry.types.Detection`) whose scores fall with their depth
    consistency (:func:`depth_consistency`) in the frame's range image: a detection at least ``cfg.depth_consistent``
    consistent keeps its score, one below it is scaled by consistency / ``cfg.depth_consistent``; ``refined``: the
    poses after ICP, held to ``cfg.depth_consistent_refined`` instead where that is set. The tolerances are
    :func:`pose_consistency`'s. objects: the :class:`detector.geometry.types.ObjectInfo`; cfg: the
    :class:`detector.geometry.types.GeometryConfig`."""
    need = cfg.depth_consistent_refined if refined and cfg.depth_consistent_refined is not None else \
        cfg.depth_consistent
    cons = np.zeros(len(detections))
    for oid in {d.obj_id for d in detections}:  # each object's poses in one pass
        rows = [k for k, d in enumerate(detections) if d.obj_id == oid]
        cons[rows] = pose_consistency(frame, objects, cfg, oid, np.stack([detections[k].R for k in rows]),
                                      np.stack([detections[k].t for k in rows]))
    return [replace(d, score=float(d.score * min(1.0, c / need))) for d, c in zip(detections, cons)]


def surface_continuation(cloud: np.ndarray, model_points: np.ndarray, model_normals: np.ndarray, R: np.ndarray,
                         t: np.ndarray, tolerance: float, reach: float, explain: float | None = None,
                         beyond: float = 0.0, min_cos: float = 0.9, neighbours: int = 16,
                         max_points: int | None = 1000, support: np.ndarray | None = None) -> tuple[int, int]:
    """How far the frame's surfaces run on past a pose's model: (explained, continued) frame point counts.

    cloud: (M,3) the frame's points, camera metres; model_points (P,3) model frame metres and model_normals (P,3)
    their outward unit normals; R (3,3), t (3,) the pose. Only the model points whose normals face the camera count
    (what the sensor could see of the posed model). The frame points in the model's box grown by ``reach`` metres
    are counted, ``max_points`` of them drawn at random where there are more (a fixed seed: the same frame and pose
    give the same counts; None: all; the counts then fall in proportion, their ratio stays). Of those within
    ``reach`` of the model, a point within ``explain`` metres of it (at least ``tolerance``; None: ``tolerance``;
    sparse model points need more) is *explained*; an unexplained one at least ``beyond`` metres from it (nearer
    ones may be the object's own points, off its model by the sensor's noise) is *continued* when it lies within
    ``tolerance`` of the tangent plane of its nearest visible model point and the frame's surface there (its normal
    from its ``neighbours`` nearest counted points) is parallel to that plane (|cos| > ``min_cos``; with fewer than
    3 counted points nothing is continued: no surface to take a normal of): the surface goes on where the model's
    ends. A real object's faces end at its outline (the frame beyond is further, nearer, or a surface at an angle:
    the table under it); a pose on part of a larger thing has the thing's surfaces continue in its faces' planes.
    support: (M,) bool, the frame points of the surface the objects stand on (the frame's dominant plane), which are
    not continued: a curved face meets the table in its tangent plane, and the table is not a larger thing the
    object is part of; unless half or more of the explained points are the table's (a pose lying in the table
    itself, which only the table explains; None: every point may be continued).
    """
    cloud = np.asarray(cloud, np.float64).reshape(-1, 3)
    X = np.asarray(model_points, np.float64) @ np.asarray(R, np.float64).T + np.asarray(t, np.float64)
    N = np.asarray(model_normals, np.float64) @ np.asarray(R, np.float64).T
    facing = np.einsum("ij,ij->i", N, -X) > 0.1 * np.linalg.norm(X, axis=1)
    X, N = X[facing], N[facing]
    if len(X) == 0 or len(cloud) == 0:
        return 0, 0
    lo, hi = X.min(axis=0) - reach, X.max(axis=0) + reach
    near = np.flatnonzero((cloud[:, 0] > lo[0]) & (cloud[:, 0] < hi[0]))  # x first: a third of the comparisons
    near = near[np.all((cloud[near, 1:] > lo[1:]) & (cloud[near, 1:] < hi[1:]), axis=1)]
    if max_points and len(near) > max_points:  # the counts' ratio, for less time; random, as a frame's points are
        # in image or voxel order, where every k-th would form a lattice (aliased bands, degenerate neighbourhoods)
        near = np.sort(np.random.default_rng(0).choice(near, max_points, replace=False))
    d, j = cKDTree(X).query(cloud[near], distance_upper_bound=reach)
    ok = np.isfinite(d)
    c, d, j = cloud[near[ok]], d[ok], j[ok]
    explained = d <= max(tolerance, explain or 0.0)
    in_plane = (d > beyond) & ~explained & (np.abs(np.einsum("ij,ij->i", c - X[j], N[j])) <= tolerance)
    if support is not None:  # the table is not a larger thing, unless the pose lies in it (mostly explained by it)
        on_support = np.asarray(support, bool)[near[ok]]
        if (on_support[explained].mean() if explained.any() else 0.0) < 0.5:
            in_plane &= ~on_support
    cand = np.flatnonzero(in_plane)
    if len(cand) == 0 or len(c) < 3:
        return int(explained.sum()), 0
    k = min(neighbours, len(c))
    _, nb = cKDTree(c).query(c[cand], k=k)
    pts = c[nb.reshape(len(cand), k)]
    centred = pts - pts.mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    parallel = np.abs(np.einsum("ij,ij->i", vecs[:, :, 0], N[j[cand]])) > min_cos
    return int(explained.sum()), int(parallel.sum())


def continuation_checked(detections: list, cloud: np.ndarray, objects, cfg, support: np.ndarray | None = None
                         ) -> list:
    """Copies of ``detections`` whose scores fall where the frame's surfaces run on past their models
    (:func:`surface_continuation`): a detection with more than ``cfg.continuation_limit`` continued frame points per
    explained one has its score scaled by the square root of limit / that ratio (a softer fall than the ratio's
    own: a right pose beside a surface in its face's plane by chance, as on a simulated LineMOD board, loses less,
    and a pose on part of a larger thing runs on past it by more). cloud: (M,3) the frame's points, camera metres;
    objects: the :class:`detector.geometry.types.ObjectInfo` (a detection of an object without surface normals,
    ``objects.surfaces``, keeps its score); cfg: the :class:`detector.geometry.types.GeometryConfig`
    (``continuation_tolerance`` metres, ``continuation_reach`` a fraction of the object's diameter). A frame point
    within 1.5 sample spacings of the model's samples counts as explained, however sparse they are. support: (M,)
    bool, the points of the surface the objects stand on, never continued (:func:`surface_continuation`; None:
    none)."""
    if not any(d.obj_id in objects.surfaces for d in detections):
        return list(detections)
    cloud = np.asarray(cloud, np.float64)
    out = []
    for d in detections:
        if d.obj_id not in objects.surfaces:
            out.append(d)
            continue
        points, normals = objects.surfaces[d.obj_id]
        spacing = objects.surface_spacing(d.obj_id)
        explained, continued = surface_continuation(cloud, points, normals, d.R, d.t, cfg.continuation_tolerance,
                                                    cfg.continuation_reach * objects.diameters[d.obj_id],
                                                    explain=1.5 * spacing, beyond=cfg.continuation_gap,
                                                    support=support)
        ratio = continued / max(explained, 1)
        scale = min(1.0, float(np.sqrt(cfg.continuation_limit / ratio))) if ratio > 0 else 1.0
        out.append(replace(d, score=float(d.score * scale)) if scale < 1.0 else d)
    return out
