"""BOP19 pose errors and Average Recall (Hodaň et al., BOP Challenge 2019/2020): small pure functions, metres.

The three errors of one estimated pose (R_est, t_est) against one ground-truth pose (R_gt, t_gt):

- VSD, Visible Surface Discrepancy: the share of the object's visible surface (in the test depth image) where the
  model's depth rendered at the estimated pose and at the true pose differ by a misalignment tolerance tau or more,
  or where only one of the two is visible; one error per tau.
- MSSD, Maximum Symmetry-aware Surface Distance: the largest distance of a model vertex under the two poses,
  minimised over the object's symmetries; metres.
- MSPD, Maximum Symmetry-aware Projection Distance: the same in the image; pixels.

Average Recall: per threshold of correctness, the estimates are matched greedily by score to the valid ground truth
(each instance once, the closest free one under the threshold), recall = matched / valid instances; AR is the mean
recall over the thresholds (and for VSD over the taus too); the BOP19 score is the mean of the three ARs. Which
estimates and instances take part (the n_top rule, the targets) is the caller's (:mod:`detector.evaluation.bop_eval`).

BOP's own units are millimetres; here everything is metres (VSD's delta 15 mm is 0.015) and pixels.
"""

from __future__ import annotations

import math

import numpy as np

from detector.evaluation.metrics import greedy_match, transform


#: VSD's visibility tolerance delta, metres (BOP19: 15 mm for every dataset but ITODD's 5 mm).
VSD_DELTA = 0.015

#: VSD's misalignment tolerances tau, fractions of the object diameter (BOP19: 0.05, 0.10, ..., 0.50).
VSD_TAUS = np.round(np.arange(1, 11) * 0.05, 2)

#: Thresholds of correctness: VSD (an error in [0, 1]) and MSSD (fraction of the diameter): 0.05 ... 0.5.
VSD_THRESHOLDS = MSSD_THRESHOLDS = np.round(np.arange(1, 11) * 0.05, 2)

#: MSPD thresholds, pixels at an image width of 640 (scaled by width / 640 for other widths): 5 ... 50.
MSPD_THRESHOLDS = np.arange(1, 11) * 5.0

#: BOP's max_sym_disc_step: the largest fraction of the diameter that the vertex furthest from a continuous
#: symmetry axis may travel between two of its discretised rotations.
MAX_SYM_DISC_STEP = 0.01


def continuous_symmetry_steps(max_step: float = MAX_SYM_DISC_STEP) -> int:
    """Rotations a continuous symmetry is discretised into (BOP: ceil(pi / max_step); 315 at 0.01)."""
    return int(math.ceil(math.pi / max_step))


def project(points: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pixel coordinates (P,2) of model points (P,3) metres under the pose R (3,3), t (3,) metres and the
    intrinsics K (3,3) pixels."""
    p = transform(points, R, t) @ np.asarray(K, np.float64).T
    return p[:, :2] / p[:, 2:3]


def _symmetric_gt_poses(R_gt, t_gt, syms: np.ndarray):
    """The true pose composed with each symmetry (S,4,4): rotations (S,3,3) and translations (S,3) metres."""
    syms = np.asarray(syms, np.float64).reshape(-1, 4, 4)
    R_gt, t_gt = np.asarray(R_gt, np.float64), np.asarray(t_gt, np.float64).reshape(3)
    return R_gt @ syms[:, :3, :3], syms[:, :3, 3] @ R_gt.T + t_gt


def mssd(R_est, t_est, R_gt, t_gt, points: np.ndarray, syms: np.ndarray) -> float:
    """MSSD, metres: min over the symmetries S (S,4,4) of the largest distance between the model vertices (P,3)
    metres under the estimated pose and under the true pose composed with S. R (3,3), t (3,) metres."""
    est = transform(points, R_est, t_est)
    return float(min(np.linalg.norm(est - transform(points, R, t), axis=1).max()
                     for R, t in zip(*_symmetric_gt_poses(R_gt, t_gt, syms))))


def mspd(R_est, t_est, R_gt, t_gt, K: np.ndarray, points: np.ndarray, syms: np.ndarray) -> float:
    """MSPD, pixels: as :func:`mssd` for the vertices' projections with K (3,3) pixels."""
    est = project(points, K, R_est, t_est)
    return float(min(np.linalg.norm(est - project(points, K, R, t), axis=1).max()
                     for R, t in zip(*_symmetric_gt_poses(R_gt, t_gt, syms))))


def spheres_overlap(t_est, t_gt, diameter: float) -> bool:
    """Whether the object's bounding spheres at the two translations (3,) metres overlap (centres closer than the
    diameter, metres). BOP's MSSD is inf for a pair that fails this."""
    return bool(np.linalg.norm(np.asarray(t_est, np.float64) - np.asarray(t_gt, np.float64)) < diameter)


def sphere_projections_overlap(t_est, t_gt, diameter: float) -> bool:
    """BOP's approximate test whether the images of the two bounding spheres (centres t (3,) metres, diameter
    metres) overlap: the centres' projections on the plane z = 1 are closer than r / z_est + r / z_gt. BOP's VSD is 1
    for a pair that fails it."""
    a, b = np.asarray(t_est, np.float64).reshape(3), np.asarray(t_gt, np.float64).reshape(3)
    if a[2] == 0 or b[2] == 0:
        return False
    r = 0.5 * diameter
    return bool(np.linalg.norm(a[:2] / a[2] - b[:2] / b[2]) < r * (1.0 / a[2] + 1.0 / b[2]))


def distance_image(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Distance from the camera centre (H,W) float64 metres of each pixel's point, from a depth image (H,W) metres
    (z, 0 = none; stays 0) and K (3,3) pixels (pixel (u, v) seen along K^-1 (u, v, 1))."""
    depth = np.asarray(depth, np.float64)
    K = np.asarray(K, np.float64)
    v, u = np.indices(depth.shape)
    return depth * np.sqrt(((u - K[0, 2]) / K[0, 0]) ** 2 + ((v - K[1, 2]) / K[1, 1]) ** 2 + 1.0)


def visible_mask(dist_test: np.ndarray, dist_model: np.ndarray, delta: float = VSD_DELTA) -> np.ndarray:
    """BOP19's visibility of a rendered model (H,W) bool: pixels where the model is rendered and lies at most
    ``delta`` metres behind the test surface, or where the test image has no depth. Distance images (H,W) metres."""
    diff = np.asarray(dist_model, np.float32) - np.asarray(dist_test, np.float32)
    return ((diff <= np.float32(delta)) | (dist_test == 0)) & (dist_model > 0)


def vsd(depth_test: np.ndarray, depth_est: np.ndarray, depth_gt: np.ndarray, K: np.ndarray, diameter: float,
        taus=VSD_TAUS, delta: float = VSD_DELTA) -> np.ndarray:
    """VSD errors (T,) in [0, 1], one per tau (T,) (fractions of ``diameter``, metres), with BOP19's step cost.

    depth_test: the test depth image (H,W) metres, 0 = none; depth_est, depth_gt: the model alone rendered at the
    estimated and the true pose (H,W) metres, 0 = background; K (3,3) pixels; delta: visibility tolerance, metres.
    The estimate's visible surface also takes the pixels where it is rendered and the true pose is visible.
    """
    d_test, d_est, d_gt = (distance_image(d, K) for d in (depth_test, depth_est, depth_gt))
    vis_gt = visible_mask(d_test, d_gt, delta)
    vis_est = visible_mask(d_test, d_est, delta) | (vis_gt & (d_est > 0))
    inter = vis_gt & vis_est
    union = int((vis_gt | vis_est).sum())
    taus = np.asarray(taus, np.float64)
    if union == 0:
        return np.ones(len(taus))
    dist = np.abs(d_gt[inter] - d_est[inter]) / diameter
    apart = union - int(inter.sum())
    return np.array([(np.count_nonzero(dist >= tau) + apart) / union for tau in taus])


def valid_instances(obj_ids: np.ndarray, visib_fract: np.ndarray, inst_count: dict[int, int]) -> np.ndarray:
    """The ground-truth instances (G,) bool of one image that BOP19 scores: per target object, its inst_count most
    visible instances (ties in instance order). obj_ids (G,) int, visib_fract (G,), inst_count {obj_id: k}."""
    left = dict(inst_count)
    valid = np.zeros(len(obj_ids), bool)
    for g in np.argsort(-np.asarray(visib_fract, np.float64), kind="stable"):
        o = int(obj_ids[g])
        if left.get(o, 0) > 0:
            valid[g], left[o] = True, left[o] - 1
    return valid


def matched_instances(scores: np.ndarray, errors: np.ndarray, valid: np.ndarray, threshold: float) -> np.ndarray:
    """Which instances (G,) bool one object's estimates match at one threshold of correctness: greedily by score
    (D,), each estimate takes the free valid instance with the smallest error under ``threshold``. errors (D,G) in
    the threshold's unit (inf: never)."""
    errors = np.asarray(errors, np.float64).reshape(len(scores), len(valid))
    errors = np.where(np.asarray(valid, bool)[None, :], errors, np.inf)
    m = greedy_match(np.asarray(scores, np.float64), errors, np.full(len(valid), float(threshold)))
    hit = np.zeros(len(valid), bool)
    hit[m[m >= 0]] = True
    return hit


def recalls(groups: list[tuple[np.ndarray, np.ndarray, np.ndarray]], thresholds) -> np.ndarray:
    """Recall (T,) at each threshold (T,) over groups [(scores (D,), errors (D,G), valid (G,) bool)], one per object
    and image: matched valid instances / valid instances (0 when there are none)."""
    n = sum(int(np.sum(v)) for _, _, v in groups)
    if n == 0:
        return np.zeros(len(thresholds))
    return np.array([sum(int(matched_instances(s, e, v, th).sum()) for s, e, v in groups) / n for th in thresholds])
