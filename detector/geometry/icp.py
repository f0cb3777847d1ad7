"""ICP refinement and the fit measures: point-to-plane ICP (open3d, loaded lazily) from a detection's pose and its
alternatives, kept only when it improves the trimmed point-to-plane fit (:func:`fit_rms`) over the same scene points,
so ICP never makes a pose worse by its own measure; the surface support that scores a two-stage detection; and
carrying the network's segmentation to the frame's full cloud (:func:`nearest_owner`, :func:`owned_points`).
Numpy and scipy; metres."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from detector.geometry.types import Detection, GeometryConfig, ObjectInfo, make_model_cloud
from detector.geometry.workers import map_threads


def icp_refine(scene_points: np.ndarray, model_points: np.ndarray, R: np.ndarray, t: np.ndarray,
               max_distance: float, iterations: int = 30, model_cloud=None, kernel: float | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Refine a pose with point-to-plane ICP (open3d) of the instance's scene points onto the model.

    The scene (a partial view) is registered to the model surface, so every scene point has a true match.
    scene_points: (S,3) camera frame, metres; model_points: (P,3) model frame, metres; R (3,3), t (3,) the
    initial T_cam_model; max_distance: correspondence distance, metres; model_cloud: a cached
    :func:`detector.geometry.types.make_model_cloud` of ``model_points``; kernel: Tukey robust-loss scale, metres
    (None: plain least squares).
    Returns the refined R (3,3), t (3,) float64.
    """
    # lazy: open3d, as in make_model_cloud
    import open3d as o3d

    # one thread inside each ICP: open3d's threaded sums of the normal equations add in a varying order, so the same
    # start could end a few hundredths of a millimetre apart from run to run, enough to flip which start fits best
    # (refine_poses runs the starts side by side instead)
    o3d.utility.set_max_threads(1)
    reg = o3d.pipelines.registration
    target = model_cloud if model_cloud is not None else make_model_cloud(model_points)
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


#: Two ICP starts are one when their rotations differ by less than this many degrees and their translations by
#: less than ``SAME_START_OFFSET`` x the diameter: ICP takes both to the same fit (RANSAC's verified hypotheses
#: are often near copies of each other: 8 starts were 5 distinct ones on average on the linemod test frames).
SAME_START_DEG = 5.0
SAME_START_OFFSET = 0.02


def distinct_poses(poses: list, diameter: float) -> list:
    """The poses [(R (3,3), t (3,) metres), ...] without those that repeat an earlier one within ``SAME_START_DEG``
    degrees and ``SAME_START_OFFSET`` x ``diameter`` (metres), in their order."""
    kept: list = []
    cos_lim = np.cos(np.radians(SAME_START_DEG))
    for R, t in poses:
        R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
        if not any((np.trace(R0.T @ R) - 1) / 2 > cos_lim and np.linalg.norm(t - t0) < SAME_START_OFFSET * diameter
                   for R0, t0 in kept):
            kept.append((R, t))
    return kept


def turned_poses(R: np.ndarray, t: np.ndarray, turns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pose (R (3,3), t (3,)) and the pose after each model-frame turn (T,4,4), as (T+1,3,3), (T+1,3): the pose
    itself first. x_cam = R (S x + s) + t, so the turned pose is (R S, R s + t)."""
    S = np.asarray(turns, np.float64).reshape(-1, 4, 4)
    Rk = np.concatenate([np.asarray(R, np.float64)[None], np.einsum("ij,kjl->kil", R, S[:, :3, :3])])
    tk = np.concatenate([np.asarray(t, np.float64)[None], S[:, :3, 3] @ np.asarray(R, np.float64).T + t])
    return Rk, tk


def icp_starts(obj_id: int, R: np.ndarray, t: np.ndarray, objects: ObjectInfo, cfg: GeometryConfig,
               alternatives: list | None = None) -> list:
    """The poses ICP starts from for one detection, [(R (3,3), t (3,) metres), ...]: its pose (R, t) first, then the
    first ``cfg.icp_starts - 1`` of its ``alternatives`` and, with ``cfg.icp_half_turns``, (R, t) turned half way
    about each of the object's axes, each near copy of an earlier start left out (:func:`distinct_poses`)."""
    starts = [(R, t)] + list(alternatives or [])[:max(cfg.icp_starts - 1, 0)]
    if cfg.icp_half_turns:  # last: of equal fits the first wins, so a turn must fit better to be kept
        Rk, tk = turned_poses(R, t, objects.half_turns(obj_id))
        starts += list(zip(Rk[1:], tk[1:]))
    return distinct_poses(starts, objects.diameters[obj_id])


def icp_from_start(scene_points: np.ndarray, obj_id: int, R: np.ndarray, t: np.ndarray, objects: ObjectInfo,
                   cfg: GeometryConfig) -> tuple[np.ndarray, np.ndarray]:
    """:func:`icp_refine` of one detection's scene points (S,3) camera metres from one start (R (3,3), t (3,)) with
    ``cfg``'s correspondence distance, iterations and kernel for ``obj_id``'s diameter, against ``objects``' cached
    model cloud: what :func:`refine_poses` runs for each start. Returns R (3,3), t (3,)."""
    dia = objects.diameters[obj_id]
    kernel = cfg.icp_kernel * dia if cfg.icp_kernel else None
    return icp_refine(scene_points, objects.model_points[obj_id], R, t, cfg.icp_distance * dia, cfg.icp_iterations,
                      objects.cloud(obj_id), kernel)


def chosen_result(fits: list[float], consistency: np.ndarray | None, margin: float | None, own: float = 0.0) -> int:
    """Which of a detection's ICP results is its candidate: fits (K,) their trimmed RMS (metres), the first from the
    detection's own pose (:func:`icp_starts`); consistency: (K,) their depth consistency in [0, 1]
    (:func:`detector.geometry.verify.pose_consistency`) or None. The best fit (the first of equal ones) among the
    results at most ``margin`` less consistent than the most consistent one, or among all without a consistency or
    a margin; but the first result where it is among them and its RMS is at most ``1 + own`` times that best one's."""
    fits = np.asarray(fits, np.float64)
    ok = np.arange(len(fits))
    if consistency is not None and margin is not None:
        consistency = np.asarray(consistency, np.float64)
        close = np.flatnonzero(consistency >= np.max(consistency) - max(margin, 0.0))
        ok = close if len(close) else ok  # none: a NaN margin or consistency, which measures nothing
    k = int(ok[np.argmin(fits[ok])])
    return 0 if ok[0] == 0 and fits[0] <= fits[k] * (1.0 + own) else k


def refine_poses(jobs: list, objects: ObjectInfo, cfg: GeometryConfig, consistency_of=None
                 ) -> list[tuple[np.ndarray, np.ndarray, bool, tuple[float, float]]]:
    """:func:`refine_pose` for several detections at once: jobs [(scene_points (S,3) camera metres, obj_id, R (3,3),
    t (3,), alternatives or None), ...]. Every job's ICP starts (:func:`icp_starts`) run side by side in one pool,
    so two cores stay busy across detections rather than idling at the end of each one's starts; each start's
    result is the same as alone (one thread inside each ICP), so the results equal calling :func:`refine_pose` on
    each job. Each job's candidate is :func:`chosen_result`'s (``cfg.icp_depth_margin``, ``cfg.icp_own_margin``)
    and is accepted when it fits better than the unrefined pose by ``cfg.icp_min_gain`` of the diameter.
    consistency_of: a function (obj_id, R (K,3,3), t (K,3) metres) -> (K,) the frame's depth consistency of K poses
    (:func:`detector.geometry.verify.pose_consistency` on the frame), which with ``cfg.icp_depth_margin`` chooses
    among a detection's results, and the candidate is then also accepted when it is more than that margin more
    consistent than the unrefined pose, whatever the fits; None: the fits alone. Returns one (R, t, accepted, (RMS
    before, RMS after)) per job, in their order."""
    flat = []  # (job index, start)
    for j, (_, oid, R, t, alts) in enumerate(jobs):
        flat += [(j, s) for s in icp_starts(oid, R, t, objects, cfg, alts)]

    for oid in {job[1] for job in jobs}:  # the model clouds built and cached here, not raced for by the threads
        objects.cloud(oid)

    def run(item):
        j, (R0, t0) = item
        return icp_from_start(jobs[j][0], jobs[j][1], R0, t0, objects, cfg)

    done = map_threads(run, flat)
    out = []
    for j, (pts, oid, R, t, _) in enumerate(jobs):
        results = [r for (i, _), r in zip(flat, done) if i == j]
        dia = objects.diameters[oid]
        tree, normals = objects.surface(oid)
        gate = cfg.icp_gate * dia
        before = fit_rms(fit_residuals(pts, tree, normals, R, t, gate), cfg.icp_trim)
        res = fit_residuals(pts, tree, normals, np.stack([r[0] for r in results]),
                            np.stack([r[1] for r in results]), gate)  # every start's result in one query
        fits = [fit_rms(r, cfg.icp_trim) for r in res]
        choose = consistency_of is not None and cfg.icp_depth_margin is not None
        cons = consistency_of(oid, np.stack([R] + [r[0] for r in results]),  # the unrefined pose, then the results
                              np.stack([t] + [r[1] for r in results])) if choose else None
        k = chosen_result(fits, None if cons is None else cons[1:], cfg.icp_depth_margin, cfg.icp_own_margin)
        after, (R1, t1) = fits[k], results[k]
        # accepted when it fits better, or when the depth prefers it to the unrefined pose (which may fit as well)
        depth_prefers = cons is not None and cons[0] < cons[1 + k] - cfg.icp_depth_margin
        if after < before - cfg.icp_min_gain * dia or depth_prefers:
            out.append((R1, t1, True, (before, after)))
        else:
            out.append((np.asarray(R, np.float64), np.asarray(t, np.float64), False, (before, after)))
    return out


def refine_pose(scene_points: np.ndarray, obj_id: int, R: np.ndarray, t: np.ndarray, objects: ObjectInfo,
                cfg: GeometryConfig, alternatives: list | None = None
                ) -> tuple[np.ndarray, np.ndarray, bool, tuple[float, float]]:
    """ICP from (R, t), kept only when it lowers the trimmed point-to-plane RMS of the same scene points
    by at least ``cfg.icp_min_gain`` of the diameter.

    scene_points: (S,3) camera frame, metres; R (3,3), t (3,) the initial T_cam_model; alternatives: other
    starting poses [(R, t), ...]; ICP runs from each of :func:`icp_starts` (the pose, some alternatives, its half
    turns) and the result that fits best is the candidate (with ``cfg.icp_own_margin``, the result from the pose
    itself unless another fits clearly better: :func:`chosen_result`; without the frame, no depth's choice). Returns R (3,3), t (3,), accepted (False: the input
    pose, unchanged) and (RMS before, RMS after) in metres.
    """
    return refine_poses([(scene_points, obj_id, R, t, alternatives)], objects, cfg)[0]


def refine_turned(points: np.ndarray, obj_id: int, R: np.ndarray, t: np.ndarray, objects: ObjectInfo,
                  cfg: GeometryConfig) -> tuple[np.ndarray, np.ndarray, float]:
    """A detection turned to a new pose (R (3,3), t (3,) metres) by a check (the colour check, the part check),
    refined by ICP from there alone, without its half turns (a start turned back could undo the turn), on the points
    ICP takes of its own points (S,3) camera frame, metres (:func:`icp_points`); and its score there, the support of
    all its points (:func:`surface_support`). Returns (R, t, score)."""
    R, t, _, _ = refine_pose(icp_points(points, cfg), obj_id, R, t, objects,
                             replace(cfg, icp_starts=1, icp_half_turns=False))
    tree, normals = objects.surface(obj_id)
    radius = support_radius(cfg.support_distance, cfg.support_floor, objects.diameters[obj_id])
    return R, t, surface_support(points, tree, normals, R, t, radius)


def icp_points(points: np.ndarray, cfg: GeometryConfig) -> np.ndarray:
    """The scene points (S,3) metres that ICP and its acceptance test use: at most ``cfg.icp_points`` of them, evenly
    spread over their order (all for ``cfg.icp_points`` <= 0)."""
    if cfg.icp_points <= 0 or len(points) <= cfg.icp_points:
        return points
    return points[np.linspace(0, len(points) - 1, cfg.icp_points).round().astype(np.int64)]


def refine(detections: list[Detection], xyz: np.ndarray, objects: ObjectInfo, cfg: GeometryConfig,
           timings: dict | None = None, cloud: np.ndarray | None = None, consistency_of=None) -> list[Detection]:
    """ICP-refined copies of ``detections`` using each one's scene points (metres).

    xyz: (K,3) the predicted points (``members`` index them); cloud: (M,3) the frame's full point cloud or None.
    A detection that carries ``points`` (rows of ``cloud``) uses those. Otherwise, with a cloud, a detection's
    scene points are the cloud points whose ``cfg.owner_votes`` nearest predicted
    points (within ``cfg.propagate``) are all its members (several times more points than the network's, and
    none next to points predicted as background or as another detection); else ``xyz[members]``. Each ICP pose
    is kept only when it fits those points better, or the frame's depth agrees with it clearly better
    (:func:`refine_poses`); the detection's ``icp`` says what
    happened. Detections with fewer than ``cfg.icp_min_points`` scene points are "skipped". consistency_of: as
    :func:`refine_poses` takes it (the frame's depth chooses among each detection's ICP results). Adds "icp" seconds.
    """
    t0 = time.perf_counter()
    propagate = cloud is not None and any(d.points is None for d in detections)  # a two-stage model's carry points
    owners = nearest_owner(xyz, cloud, cfg.propagate, cfg.owner_votes) if propagate else None
    points = []
    for d in detections:
        if d.points is not None and cloud is not None:
            points.append(np.asarray(cloud)[d.points])
        elif owners is not None:
            points.append(np.asarray(cloud)[owned_points(owners, d.members, len(xyz))])
        else:
            points.append(xyz[d.members])
    todo = [k for k, pts in enumerate(points) if len(pts) >= cfg.icp_min_points]
    refined = dict(zip(todo, refine_poses([(icp_points(points[k], cfg), detections[k].obj_id, detections[k].R,
                                             detections[k].t, detections[k].alternatives) for k in todo],
                                           objects, cfg, consistency_of)))
    out = []
    for k, (d, pts) in enumerate(zip(detections, points)):
        if k not in refined:
            out.append(replace(d, icp="skipped"))
            continue
        R, t, ok, _ = refined[k]
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
