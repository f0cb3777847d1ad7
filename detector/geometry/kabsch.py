"""Rigid fits: reflection-safe (weighted) Kabsch, batched over many point sets, and RANSAC over 3-point Kabsch
hypotheses (:func:`ransac_kabsch`), which stage 2 uses to turn model-coordinate correspondences into a pose.
Pure numpy; metres."""

from __future__ import annotations

import numpy as np


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


def ransac_draws(n: int, hypotheses: int, rng: np.random.Generator, score_points: int | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The random choices of :func:`ransac_kabsch` over n correspondences: the rows it scores on, sub (ns,) int64
    (at most ``score_points`` of them, a random subset, sorted; all for None), and the three rows of each
    hypothesis, idx (hypotheses, 3) int64 rows of the n; distinct within a hypothesis where ns < 64 (above, repeats
    are rare and harmless). Drawn apart from the fit so that fits can run on threads with the draws of a fixed
    order."""
    sub = np.arange(n) if score_points is None or n <= score_points else \
        np.sort(rng.choice(n, score_points, replace=False))
    ns = len(sub)
    idx = sub[np.argsort(rng.random((hypotheses, ns)), axis=1)[:, :3] if ns < 64 else
              rng.integers(0, ns, (hypotheses, 3))]
    return sub, idx


def ransac_kabsch(model_pts: np.ndarray, scene_pts: np.ndarray, weights: np.ndarray, threshold: float,
                  rng: np.random.Generator | None, hypotheses: int = 128, refits: int = 3, keep: int = 1,
                  score_points: int | None = None, draws: tuple[np.ndarray, np.ndarray] | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """A pose from noisy 3D-3D correspondences: RANSAC over 3-point Kabsch hypotheses, then weighted refits.

    model_pts: (n,3) model frame, metres (predicted model coordinates); scene_pts: (n,3) camera frame, metres;
    weights: (n,) >= 0 (foreground probabilities); threshold: metres, a correspondence is an inlier when
    ``|R m + t - p|`` is under it. The hypothesis with the largest inlier weight wins; it is refitted on its
    inliers ``refits`` times (weighted Kabsch). Returns R (3,3), t (3,) float64 and the inlier mask (n,) bool;
    with ``keep`` > 1, a list of the ``keep`` best hypotheses so refitted, best first (for a verification step).
    score_points: hypotheses are drawn from, and scored on, at most this many of the correspondences (a random
    subset; None = all); the refits use all of them. draws: :func:`ransac_draws`' (sub, idx) for these n, drawn
    before (then ``rng``, ``hypotheses`` and ``score_points`` are not used); None: drawn here from ``rng``. Needs
    n >= 3.
    """
    m, p = np.asarray(model_pts, np.float64), np.asarray(scene_pts, np.float64)
    w = np.asarray(weights, np.float64)
    n = len(m)
    sub, idx = draws if draws is not None else ransac_draws(n, hypotheses, rng, score_points)
    ns = len(sub)
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
