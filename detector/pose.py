"""From per-point network output to 6-DoF poses (paper section "6-DOF Pose Estimation").

Pipeline: drop background points and points with confidence under ``tau``; each kept point's control
points = point + offsets; per class, the predicted box centres vote on a voxel grid and connected
occupied cells form instances (so several instances of one object are found); a robust aggregate of
the instance's votes is fitted to the model's 9 control points with a confidence-weighted,
reflection-safe Kabsch; non-maximum suppression by confidence; optional point-to-plane ICP (open3d)
between the instance's scene points and the model points, kept only when it improves the trimmed
point-to-plane fit (:func:`fit_rms`) over the same scene points, so ICP never makes a pose worse by its
own measure.

Pure numpy (open3d only inside :func:`icp_refine`); metres; poses map model points into the camera frame
(``x_cam = R @ x_model + t``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
from scipy.spatial import cKDTree

# the 27 offsets of a voxel's 26-neighbourhood (and itself)
_NEIGHBOURS = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)


@dataclass
class PoseConfig:
    """Options of the pose stage.

    tau: confidence threshold; cell: voting voxel size, metres; min_votes: fewest votes an instance needs;
    mode_radius: > 0 clusters the centre votes around their density modes within this fraction of the diameter
    (:func:`vote_modes`; instances side by side stay apart) instead of in touching ``cell`` voxels;
    nms_fraction: centres closer than this fraction of the object's diameter are one detection;
    inlier_fraction: votes farther than this fraction of the diameter from the median are outliers;
    icp: refine with ICP; icp_distance: ICP correspondence distance as a fraction of the diameter;
    icp_kernel: Tukey robust-loss scale as a fraction of the diameter (0 = plain least squares);
    icp_iterations: ICP iteration limit; icp_min_points: fewest scene points to run ICP;
    icp_trim: share of the scene points (the best-fitting ones) whose point-to-plane RMS decides whether
    the ICP pose is kept (see :func:`fit_rms`); icp_gate: a scene point farther than this fraction of the
    diameter from every model point counts as an outlier at that distance; icp_starts: ICP runs from the
    detection's pose and from up to ``icp_starts - 1`` of its ``alternatives`` and keeps the best-fitting result
    (a wrong-way first pose is a local minimum that ICP alone cannot leave); icp_min_gain: the ICP pose is kept
    only when it lowers that trimmed RMS by at least this fraction of the diameter (a smaller gain is within what
    the model's point sampling itself contributes, and on a few points of a smooth surface ICP can slide a right
    pose by centimetres for such a gain); icp_points: ICP and its acceptance test use at most this many of a
    detection's scene points, evenly spread over them (0 = all; their cost grows with the points, and a stage 2
    that pools several crop samples hands over several hundred), the score after ICP uses them all;
    propagate: metres, a frame point belongs to a detection when its ``owner_votes`` nearest predicted points
    within this distance are all that detection's members (ICP points);
    centre_votes: instances from the box-centre votes alone (a two-stage model's stage 1, whose corners are
    not trained): the detection's centre is their robust mean and its orientation is left to stage 2;
    min_score: final detections scoring less are dropped (with ICP, by their score after ICP);
    min_score_unrefined: the threshold of the unrefined detections (None: ``min_score``); a two-stage detection's
    support before ICP is lower than after it, so the two get thresholds of their own;
    support_distance: a two-stage detection's score is the share of its points within this fraction of the
    diameter of the model surface under its pose (:func:`surface_support`), recomputed after ICP;
    support_floor: metres, that distance is at least this much (:func:`support_radius`): a depth sensor's error
    does not shrink with the object, and 2 % of a small object's diameter (2 mm for the ape) is below a Kinect
    v1's median depth error near 1 m (2.4 mm), so right poses of small objects would score low.
    """

    tau: float = 0.8
    cell: float = 0.02
    min_votes: int = 3
    mode_radius: float = 0.0
    nms_fraction: float = 0.5
    inlier_fraction: float = 0.15
    icp: bool = False
    icp_distance: float = 0.2
    icp_kernel: float = 0.0
    icp_iterations: int = 30
    icp_min_points: int = 30
    icp_trim: float = 0.7
    icp_gate: float = 0.05
    icp_starts: int = 8
    icp_min_gain: float = 0.001
    icp_points: int = 0
    support_distance: float = 0.02
    support_floor: float = 0.004
    propagate: float = 0.01
    owner_votes: int = 3
    centre_votes: bool = False
    min_score: float = 0.0
    min_score_unrefined: float | None = None


@dataclass
class Detection:
    """One detected object instance.

    obj_id: object id; score: mean confidence of its votes x share of kept votes in [0, 1];
    R: (3,3) float64; t: (3,) float64 metres (model -> camera); support: number of votes;
    control_points: (9,3) float64 metres, the aggregated predicted control points (camera frame);
    members: (S,) int64 rows of the prediction arrays that voted for it; refined: the ICP pose was kept;
    icp: what ICP did - "" (not run), "accepted", "rejected" (it did not improve the fit: pose unchanged),
    "skipped" (too few scene points);
    points: (P,) int64 rows of the frame cloud that are this instance's (a two-stage model's crop foreground),
    or None (ICP then carries ``members`` to the cloud); alternatives: other candidate poses [(R, t), ...], best
    first (a two-stage model's other verified RANSAC hypotheses), from which ICP also starts.
    """

    obj_id: int
    score: float
    R: np.ndarray
    t: np.ndarray
    support: int
    control_points: np.ndarray
    members: np.ndarray = field(repr=False)
    refined: bool = False
    icp: str = ""
    points: np.ndarray | None = field(default=None, repr=False)
    alternatives: list | None = field(default=None, repr=False)

    @property
    def pose(self) -> np.ndarray:
        """(4,4) float64 T_cam_model, metres."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T


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


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares rigid transform with ``dst ~ R @ src + t`` (SVD, never a reflection).

    src, dst: (n,3) metres, n >= 3 not collinear; weights: (n,) >= 0 or None. Returns R (3,3), t (3,) float64.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    H = (src - cs).T @ ((dst - cd) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cd - R @ cs


def _proper_rotations(M: np.ndarray) -> np.ndarray:
    """The rotations R (H,3,3) that best map the centred source onto the centred target of H cross-covariances
    ``M[h] = sum (s - cs)(d - cd)^T`` (H,3,3): ``V diag(1, 1, det(V U^T)) U^T`` from the SVD, never a reflection."""
    U, _, Vt = np.linalg.svd(M)
    V = np.swapaxes(Vt, 1, 2)
    d = np.sign(np.linalg.det(V) * np.linalg.det(U))  # det(V U^T)
    d[d == 0] = 1.0
    V[:, :, 2] *= d[:, None]
    return V @ np.swapaxes(U, 1, 2)


def kabsch_batch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unweighted Kabsch for H point sets at once: ``dst[h] ~ R[h] @ src[h] + t[h]``, never a reflection.

    src, dst: (H,m,3) metres. Returns R (H,3,3), t (H,3) float64.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    cs, cd = src.mean(1), dst.mean(1)
    R = _proper_rotations(np.swapaxes(src - cs[:, None], 1, 2) @ (dst - cd[:, None]))
    return R, cd - (R @ cs[:, :, None])[:, :, 0]


def weighted_kabsch_shared(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Kabsch for K weightings of the same correspondences at once: ``dst ~ R[k] @ src + t[k]`` under
    weights[k] (the same solution as :func:`kabsch` for each row, never a reflection).

    src, dst: (n,3) metres; weights: (K,n) >= 0, each row with a positive sum. Returns R (K,3,3), t (K,3) float64.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    w = np.asarray(weights, np.float64)
    w = w / w.sum(1, keepdims=True)
    cs, cd = w @ src, w @ dst  # (K,3)
    M = (w[:, :, None] * src).transpose(0, 2, 1) @ dst - cs[:, :, None] * cd[:, None, :]  # sum w (s - cs)(d - cd)^T
    R = _proper_rotations(M)
    return R, cd - (R @ cs[:, :, None])[:, :, 0]


def _sq_residuals(R: np.ndarray, t: np.ndarray, m: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Squared distances ``|R[h] m + t[h] - p|^2`` (H,n) of H poses R (H,3,3), t (H,3) over the correspondences
    m, p (n,3) metres (matrix products: an einsum over the H x n x 3 x 3 terms is several times slower)."""
    d = m @ np.swapaxes(R, 1, 2) + (t[:, None] - p)
    return np.einsum("hni,hni->hn", d, d)


def ransac_kabsch(model_pts: np.ndarray, scene_pts: np.ndarray, weights: np.ndarray, threshold: float,
                  rng: np.random.Generator, hypotheses: int = 128, refits: int = 3, keep: int = 1,
                  score_points: int | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """A pose from noisy 3D-3D correspondences: RANSAC over 3-point Kabsch hypotheses, then weighted refits.

    model_pts: (n,3) model frame, metres (predicted model coordinates); scene_pts: (n,3) camera frame, metres;
    weights: (n,) >= 0 (foreground probabilities); threshold: metres, a correspondence is an inlier when
    ``|R m + t - p|`` is under it. The hypothesis with the largest inlier weight wins; it is refitted on its
    inliers ``refits`` times (weighted Kabsch). Returns R (3,3), t (3,) float64 and the inlier mask (n,) bool;
    with ``keep`` > 1, a list of the ``keep`` best hypotheses so refitted, best first (for a verification step).
    score_points: hypotheses are drawn from, and scored on, at most this many of the correspondences (a random
    subset; None = all); the refits use all of them. Needs n >= 3.
    """
    m, p = np.asarray(model_pts, np.float64), np.asarray(scene_pts, np.float64)
    w = np.asarray(weights, np.float64)
    n = len(m)
    sub = np.arange(n) if score_points is None or n <= score_points else \
        np.sort(rng.choice(n, score_points, replace=False))
    ns = len(sub)
    # three distinct points per hypothesis where repeats would be common; above 64 points they are rare and harmless
    idx = sub[np.argsort(rng.random((hypotheses, ns)), axis=1)[:, :3] if ns < 64 else
              rng.integers(0, ns, (hypotheses, 3))]
    Rh, th = kabsch_batch(m[idx], p[idx])
    inside = _sq_residuals(Rh, th, m[sub], p[sub]) < threshold * threshold  # (H, ns)
    score = inside @ w[sub]
    best = np.argsort(-score, kind="stable")[:max(keep, 1)]
    R, t = Rh[best], th[best]
    inl = inside[best] if ns == n else _sq_residuals(R, t, m, p) < threshold * threshold  # (K, n)
    active = np.ones(len(best), bool)
    for _ in range(refits):  # all kept hypotheses at once; one whose inliers fall under 3 stays where it is
        active &= inl.sum(1) >= 3
        if not active.any():
            break
        # only the active rows: an inactive one may have no inlier left, and its zero weights would give a NaN
        # matrix that fails the whole batch's SVD (R and t are Rh[best]'s own copies, so writing into them is safe)
        R[active], t[active] = weighted_kabsch_shared(m, p, np.where(inl[active], w + 1e-9, 0.0))
        new = _sq_residuals(R, t, m, p) < threshold * threshold
        inl = np.where(active[:, None], new, inl)
    out = [(R[k], t[k], inl[k]) for k in range(len(best))]
    return out if keep > 1 else out[0]


def nms(detections: list[Detection], diameters: dict[int, float], fraction: float) -> list[Detection]:
    """Non-maximum suppression by score: drop a detection whose centre lies within ``fraction`` of the
    object's diameter (metres, per obj_id) of a higher-scoring detection of the same object. Returns kept, by score."""
    kept: list[Detection] = []
    for d in sorted(detections, key=lambda d: -d.score):
        if all(k.obj_id != d.obj_id or np.linalg.norm(k.t - d.t) >= fraction * diameters[d.obj_id] for k in kept):
            kept.append(d)
    return kept


def _model_cloud(model_points: np.ndarray):
    """An open3d cloud of model points (metres) with estimated normals (their sign does not matter)."""
    # lazy: open3d loads in about a second; only ICP and the fit measure need it
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(model_points, np.float64)))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(12))
    return pc


def icp_refine(scene_points: np.ndarray, model_points: np.ndarray, R: np.ndarray, t: np.ndarray,
               max_distance: float, iterations: int = 30, model_cloud=None, kernel: float | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Refine a pose with point-to-plane ICP (open3d) of the instance's scene points onto the model.

    The scene (a partial view) is registered to the model surface, so every scene point has a true match.
    scene_points: (S,3) camera frame, metres; model_points: (P,3) model frame, metres; R (3,3), t (3,) the
    initial T_cam_model; max_distance: correspondence distance, metres; model_cloud: a cached
    :func:`_model_cloud` of ``model_points``; kernel: Tukey robust-loss scale, metres (None: plain least squares).
    Returns the refined R (3,3), t (3,) float64.
    """
    # lazy: open3d, as in _model_cloud
    import open3d as o3d

    reg = o3d.pipelines.registration
    target = model_cloud if model_cloud is not None else _model_cloud(model_points)
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(scene_points, np.float64)))
    T0 = np.eye(4)
    T0[:3, :3], T0[:3, 3] = R, t
    init = np.linalg.inv(T0)  # camera -> model
    est = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=kernel)) if kernel else \
        reg.TransformationEstimationPointToPlane()
    res = reg.registration_icp(source, target, max_distance, init, est,
                               reg.ICPConvergenceCriteria(max_iteration=iterations))
    if len(res.correspondence_set) < 3:
        return np.asarray(R, np.float64), np.asarray(t, np.float64)
    T = np.linalg.inv(np.asarray(res.transformation))
    return T[:3, :3], T[:3, 3]


def fit_residuals(scene_points: np.ndarray, model_tree, model_normals: np.ndarray, R: np.ndarray, t: np.ndarray,
                  gate: float) -> np.ndarray:
    """Point-to-plane distance of each scene point to the model surface under the pose (R, t).

    scene_points: (S,3) camera frame, metres; model_tree: a scipy cKDTree of the model points (P,3) model frame;
    model_normals: (P,3) unit normals; R (3,3), t (3,) T_cam_model, or R (K,3,3), t (K,3) for K poses at once;
    gate: metres, a point whose nearest model point is farther gets ``gate``. Returns (S,) float64 metres, each at
    most ``gate`` ((K,S) for K poses).
    """
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
    many = R.ndim == 3
    Rk, tk = (R, t) if many else (R[None], t[None])
    x = (np.asarray(scene_points, np.float64)[None] - tk[:, None]) @ Rk  # model frame, (K,S,3)
    flat = x.reshape(-1, 3)
    d, j = model_tree.query(flat, k=1, distance_upper_bound=gate)
    found = np.isfinite(d)
    r = np.full(len(flat), gate)
    jj = j[found]
    r[found] = np.minimum(np.abs(np.einsum("ij,ij->i", flat[found] - model_tree.data[jj], model_normals[jj])), gate)
    r = r.reshape(len(Rk), -1)
    return r if many else r[0]


def fit_rms(residuals: np.ndarray, trim: float) -> float:
    """Least-trimmed RMS: the RMS of the smallest ``trim`` share (at least 3) of the residuals (S,) metres.

    Robust to up to 1 - trim of the points being wrong (a support plane or a neighbour that slipped into the
    segment): a pose that such points drag away fits the object's own points worse, and this says so.
    """
    r = np.sort(np.asarray(residuals, np.float64))
    k = min(len(r), max(3, int(np.ceil(trim * len(r)))))
    return float(np.sqrt(np.mean(r[:k] ** 2))) if k else float("inf")


def support_radius(fraction: float, floor: float, diameter: float) -> float:
    """The distance (metres) within which a point counts as explained by the model surface: ``fraction`` of the
    ``diameter`` (metres), but at least ``floor`` metres (the sensor's noise)."""
    return max(fraction * diameter, floor)


def surface_support(points: np.ndarray, model_tree, model_normals: np.ndarray, R: np.ndarray, t: np.ndarray,
                    distance: float) -> float:
    """Share of the points (S,3) camera frame, metres, within ``distance`` metres of the model surface under
    (R, t) (point-to-plane, see :func:`fit_residuals`): how well a pose explains a detection's own points.
    0 for no points."""
    if len(points) == 0:
        return 0.0
    return float(np.mean(fit_residuals(points, model_tree, model_normals, R, t, 2.5 * distance) < distance))


@dataclass
class ObjectInfo:
    """What the pose stage needs of each object, by obj_id.

    control_points: {obj_id: (9,3) metres model frame}; diameters: {obj_id: metres};
    model_points: {obj_id: (P,3) metres model frame}.
    """

    control_points: dict[int, np.ndarray]
    diameters: dict[int, float]
    model_points: dict[int, np.ndarray]
    _clouds: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_table(cls, table) -> "ObjectInfo":
        """From an ``argen.h5.ObjectTable`` or the checkpoint's plain-list object dict."""
        get = (lambda k: table[k]) if isinstance(table, dict) else (lambda k: getattr(table, k))
        ids = [int(i) for i in get("ids")]
        cps, dia, mp = get("control_points"), get("diameters"), get("model_points")
        return cls({i: np.asarray(cps[k], np.float64) for k, i in enumerate(ids)},
                   {i: float(dia[k]) for k, i in enumerate(ids)},
                   {i: np.asarray(mp[k], np.float64) for k, i in enumerate(ids)})

    def cloud(self, obj_id: int):
        """The cached open3d model cloud with normals of ``obj_id``."""
        if obj_id not in self._clouds:
            self._clouds[obj_id] = _model_cloud(self.model_points[obj_id])
        return self._clouds[obj_id]

    def surface(self, obj_id: int):
        """(cKDTree of the model points, (P,3) their unit normals) of ``obj_id``, cached: the fit measure's model."""
        key = ("surface", obj_id)
        if key not in self._clouds:
            self._clouds[key] = (cKDTree(np.asarray(self.model_points[obj_id], np.float64)),
                                 np.asarray(self.cloud(obj_id).normals))
        return self._clouds[key]


def detect(xyz: np.ndarray, obj_ids: np.ndarray, confidence: np.ndarray, control_points: np.ndarray,
           objects: ObjectInfo, cfg: PoseConfig, timings: dict | None = None) -> list[Detection]:
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
    dets = nms(dets, objects.diameters, cfg.nms_fraction)
    if timings is not None:
        timings["voting"] = timings.get("voting", 0.0) + t1 - t0
        timings["kabsch"] = timings.get("kabsch", 0.0) + time.perf_counter() - t1
    return dets


def nearest_owner(xyz: np.ndarray, cloud: np.ndarray, radius: float, k: int = 1) -> np.ndarray:
    """The ``k`` nearest predicted points of every cloud point (carries the network's segmentation to all points).

    xyz: (K,3) metres, the predicted points; cloud: (M,3) metres; radius: metres, farther predicted points are
    not neighbours. Returns (M,) int64 row of ``xyz`` (k = 1) or (M,k) rows, -1 for none.
    """
    dist, owner = cKDTree(np.asarray(xyz, np.float64)).query(np.asarray(cloud, np.float64), k=k,
                                                            distance_upper_bound=radius)
    return np.where(np.isfinite(dist), owner, -1).astype(np.int64)


def owned_points(owners: np.ndarray, members: np.ndarray, num_predicted: int) -> np.ndarray:
    """Cloud points that belong to a detection: all their neighbours (see :func:`nearest_owner`, -1 = none) are
    its members, and they have at least one. owners: (M,) or (M,k) int64; members: (S,) rows of the K predicted
    points. Returns (M,) bool. A point next to background or another detection's points is left out."""
    owners = owners.reshape(len(owners), -1)
    is_member = np.zeros(num_predicted + 1, bool)  # the extra last entry is the "no owner" row -1
    is_member[members] = True
    none = owners < 0
    return np.all(is_member[owners] | none, axis=1) & ~np.all(none, axis=1)


def refine_pose(scene_points: np.ndarray, obj_id: int, R: np.ndarray, t: np.ndarray, objects: ObjectInfo,
                cfg: PoseConfig, alternatives: list | None = None
                ) -> tuple[np.ndarray, np.ndarray, bool, tuple[float, float]]:
    """ICP from (R, t), kept only when it lowers the trimmed point-to-plane RMS of the same scene points
    by at least ``cfg.icp_min_gain`` of the diameter.

    scene_points: (S,3) camera frame, metres; R (3,3), t (3,) the initial T_cam_model; alternatives: other
    starting poses [(R, t), ...], of which the first ``cfg.icp_starts - 1`` are also refined; the ICP result
    that fits best is the candidate. Returns R (3,3), t (3,), accepted (False: the input pose, unchanged) and
    (RMS before, RMS after) in metres.
    """
    dia = objects.diameters[obj_id]
    tree, normals = objects.surface(obj_id)
    gate = cfg.icp_gate * dia
    before = fit_rms(fit_residuals(scene_points, tree, normals, R, t, gate), cfg.icp_trim)
    starts = [(R, t)] + list(alternatives or [])[:max(cfg.icp_starts - 1, 0)]
    results = [icp_refine(scene_points, objects.model_points[obj_id], R0, t0, cfg.icp_distance * dia,
                          cfg.icp_iterations, objects.cloud(obj_id), cfg.icp_kernel * dia if cfg.icp_kernel else None)
               for R0, t0 in starts]
    res = fit_residuals(scene_points, tree, normals, np.stack([r[0] for r in results]),
                        np.stack([r[1] for r in results]), gate)  # every start's result in one query
    fits = [fit_rms(r, cfg.icp_trim) for r in res]
    k = int(np.argmin(fits))  # the first of equal fits, as before
    after, (R1, t1) = fits[k], results[k]
    if after < before - cfg.icp_min_gain * dia:
        return R1, t1, True, (before, after)
    return np.asarray(R, np.float64), np.asarray(t, np.float64), False, (before, after)


def refine(detections: list[Detection], xyz: np.ndarray, objects: ObjectInfo, cfg: PoseConfig,
           timings: dict | None = None, cloud: np.ndarray | None = None) -> list[Detection]:
    """ICP-refined copies of ``detections`` using each one's scene points (metres).

    xyz: (K,3) the predicted points (``members`` index them); cloud: (M,3) the frame's full point cloud or None.
    A detection that carries ``points`` (rows of ``cloud``) uses those. Otherwise, with a cloud, a detection's
    scene points are the cloud points whose ``cfg.owner_votes`` nearest predicted
    points (within ``cfg.propagate``) are all its members (several times more points than the network's, and
    none next to points predicted as background or as another detection); else ``xyz[members]``. Each ICP pose
    is kept only when it fits those points better (:func:`refine_pose`); the detection's ``icp`` says what
    happened. Detections with fewer than ``cfg.icp_min_points`` scene points are "skipped". Adds "icp" seconds.
    """
    t0 = time.perf_counter()
    propagate = cloud is not None and any(d.points is None for d in detections)  # a two-stage model's carry points
    owners = nearest_owner(xyz, cloud, cfg.propagate, cfg.owner_votes) if propagate else None
    out = []
    for d in detections:
        if d.points is not None and cloud is not None:
            pts = np.asarray(cloud)[d.points]
        elif owners is not None:
            pts = np.asarray(cloud)[owned_points(owners, d.members, len(xyz))]
        else:
            pts = xyz[d.members]
        if len(pts) < cfg.icp_min_points:
            out.append(replace(d, icp="skipped"))
            continue
        fit = pts if cfg.icp_points <= 0 or len(pts) <= cfg.icp_points else \
            pts[np.linspace(0, len(pts) - 1, cfg.icp_points).round().astype(np.int64)]
        R, t, ok, _ = refine_pose(fit, d.obj_id, d.R, d.t, objects, cfg, d.alternatives)
        score = d.score
        if d.points is not None:  # a two-stage detection: its score is the support of its points, at the new pose
            tree, normals = objects.surface(d.obj_id)
            score = surface_support(pts, tree, normals, R, t,
                                    support_radius(cfg.support_distance, cfg.support_floor, objects.diameters[d.obj_id]))
        out.append(replace(d, R=R, t=t, score=score, refined=ok, icp="accepted" if ok else "rejected"))
    if timings is not None:
        timings["icp"] = timings.get("icp", 0.0) + time.perf_counter() - t0
    return out


def icp_counts(detections: list[Detection]) -> dict[str, int]:
    """How many ``detections`` had their ICP pose accepted, rejected or skipped: {"accepted", "rejected", "skipped"}."""
    return {k: sum(d.icp == k for d in detections) for k in ("accepted", "rejected", "skipped")}
