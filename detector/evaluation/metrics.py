"""Pose-error metrics and the evaluation protocols of the paper.

ADD (Hinterstoisser et al.): mean distance of the model points under the true and the estimated pose.
ADD-S: mean distance to the closest model point (for symmetric objects, eq. 1 of the paper). A pose is
correct when its error is under k x diameter (k = 0.10 for Table II, 0.10/0.15/0.30 for Table III).
Which pose counts for ADD: per object and frame only the k best-scoring detections, k the number of its instances
that count (BOP19's n_top rule), matched greedily by score; a user reads the top-scoring pose, so a higher-scoring
pose that is wrong makes the instance wrong even when a lower-scoring detection lies on it.
Multi-instance data (LC-HF): all detections matched greedily by score to ground-truth instances at 15 % of the
diameter; precision, recall and F1 over all detections and instances. Metres throughout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


THRESHOLDS = (0.10, 0.15, 0.30)


def transform(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points (P,3) metres mapped by R (3,3), t (3,): (P,3)."""
    return np.asarray(points, np.float64) @ np.asarray(R, np.float64).T + np.asarray(t, np.float64)


def add(model_points: np.ndarray, R_gt, t_gt, R_est, t_est) -> float:
    """ADD: mean distance between corresponding model points (P,3) under the true and estimated pose, metres."""
    return float(np.linalg.norm(transform(model_points, R_gt, t_gt) - transform(model_points, R_est, t_est),
                                axis=1).mean())


def adds(model_points: np.ndarray, R_gt, t_gt, R_est, t_est) -> float:
    """ADD-S: mean distance of each estimated model point (P,3) to the closest true one (KD-tree), metres."""
    d, _ = cKDTree(transform(model_points, R_gt, t_gt)).query(transform(model_points, R_est, t_est), k=1)
    return float(d.mean())


def pose_error(model_points: np.ndarray, symmetric: bool, R_gt, t_gt, R_est, t_est) -> float:
    """ADD-S for a symmetric object, ADD otherwise; metres."""
    return (adds if symmetric else add)(model_points, R_gt, t_gt, R_est, t_est)


def accuracy(errors: np.ndarray, diameters: np.ndarray, k: float) -> float:
    """Share of errors (n,) metres under k x diameters (n,) metres (inf = missed); nan when n = 0."""
    errors = np.asarray(errors, np.float64)
    return float(np.mean(errors < k * np.asarray(diameters, np.float64))) if len(errors) else float("nan")


def accuracy_curve(errors: np.ndarray, diameters: np.ndarray, ks: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Accuracy against threshold: ks (T,) fractions of the diameter (default 0..0.5) and accuracy (T,)."""
    ks = np.linspace(0.0, 0.5, 51) if ks is None else np.asarray(ks, np.float64)
    rel = np.asarray(errors, np.float64) / np.asarray(diameters, np.float64)
    acc = (rel[None, :] < ks[:, None]).mean(1) if len(rel) else np.full(len(ks), np.nan)
    return ks, acc


def greedy_match(scores: np.ndarray, error: np.ndarray, limit: np.ndarray | None = None) -> np.ndarray:
    """Match detections to ground truth greedily by score, each ground truth at most once.

    scores: (D,); error: (D,G) metres, inf where the pair cannot match (other object); limit: (G,) metres, a pair
    matches only with error under it (None: any finite error). Returns (D,) int64 matched GT column or -1.
    """
    D, G = error.shape
    match = np.full(D, -1, np.int64)
    free = np.ones(G, bool)
    lim = np.full(G, np.inf) if limit is None else np.asarray(limit, np.float64)
    for d in np.argsort(-np.asarray(scores), kind="stable"):
        ok = free & np.isfinite(error[d]) & (error[d] < lim)
        if ok.any():
            g = int(np.flatnonzero(ok)[np.argmin(error[d][ok])])
            match[d], free[g] = g, False
    return match


def top_k(scores: np.ndarray, k: int) -> np.ndarray:
    """Indices (min(k, D),) int64 of the k highest of scores (D,), best first; equal scores keep their order (as
    BOP's toolkit, whose sort is stable)."""
    return np.argsort(-np.asarray(scores, np.float64), kind="stable")[:max(int(k), 0)].astype(np.int64)


@dataclass
class FrameMatch:
    """Evaluation of one object's detections in one frame against its ground truth (G instances, D detections).

    gt_error: (G,) metres, the error of the detection matched to each instance: only the k best-scoring detections
    take part (k = valid instances), matched greedily by score to valid instances, pairs under ``k_add_limit`` x
    diameter; inf when none (and for invalid instances) - used for ADD accuracy and the curve; tp: detections (all
    of them) matched to a valid instance under ``k_f1`` x diameter (F1 protocol); num_det: detections counted (those
    matched to an ignored instance are left out); num_gt: valid instances.
    """

    gt_error: np.ndarray
    tp: int
    num_det: int
    num_gt: int


def match_frame(scores: np.ndarray, error: np.ndarray, diameters: np.ndarray, valid: np.ndarray | None = None,
                k_f1: float = 0.15, k_add_limit: float = 0.5) -> FrameMatch:
    """Both protocols for one object in one frame. scores (D,), error (D,G) metres, diameters (G,) metres;
    valid: (G,) bool instances that count (e.g. visible enough); the others are ignored, as are detections of them.

    ADD: the k = valid.sum() best-scoring detections only (BOP19's n_top rule: what a user would read), each matched
    greedily by score to the closest free valid instance within ``k_add_limit`` of the diameter (the curve's range).
    A higher-scoring wrong pose uses up its place, so a lower-scoring right one behind it does not count.
    F1: every detection, greedy by score at ``k_f1``.
    """
    error = np.asarray(error, np.float64).reshape(len(scores), len(diameters))
    scores = np.asarray(scores, np.float64)
    diameters = np.asarray(diameters, np.float64)
    valid = np.ones(len(diameters), bool) if valid is None else np.asarray(valid, bool)
    cols = np.flatnonzero(valid)
    top = top_k(scores, len(cols))
    m = greedy_match(scores[top], error[np.ix_(top, cols)], k_add_limit * diameters[cols])
    gt_error = np.full(len(diameters), np.inf)
    hit = m >= 0
    gt_error[cols[m[hit]]] = error[top[hit], cols[m[hit]]]
    f = greedy_match(scores, error, k_f1 * diameters)
    ignored = (f >= 0) & ~valid[np.maximum(f, 0)] if len(valid) else np.zeros(len(f), bool)
    tp = int(((f >= 0) & ~ignored).sum())
    return FrameMatch(gt_error, tp, int(len(scores) - ignored.sum()), int(valid.sum()))


def prf(tp: int, num_det: int, num_gt: int) -> dict[str, float]:
    """Precision, recall and F1 from counts (0 where undefined)."""
    p = tp / num_det if num_det else 0.0
    r = tp / num_gt if num_gt else 0.0
    return {"precision": p, "recall": r, "f1": 2 * p * r / (p + r) if p + r else 0.0}
