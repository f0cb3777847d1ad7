"""PointNet++ sampling and neighbour ops: farthest point sampling, ball query, grouping, 3-NN interpolation.

Two paths compute the indices:

* :func:`precompute_indices` (numpy, one cloud): exact FPS from ``fpsample`` and neighbours from a
  ``pykdtree`` KD-tree; meant for DataLoader workers and inference on CPU, where sampling would otherwise dominate
  the forward pass.
* :func:`compute_indices_torch` (torch, batched, any device): the GPU path, or when no indices are given.

Conventions shared by both (so on clouds of up to :data:`EXACT_FPS_MAX_POINTS` points they give the same
indices, up to floating-point near-ties):

* FPS starts at index 0 and each next index is the point farthest (squared Euclidean) from those chosen;
  ties go to the lowest index. On clouds of more than :data:`EXACT_FPS_MAX_POINTS` points the numpy path uses
  fpsample's tree-based FPS instead: as exact (every next point is a farthest one) and 12 to 22 times faster, but
  started at a point of its own choosing (fpsample 0.3 reads its ``start_idx`` as a place in its tree, not in the
  cloud; the start is still a function of the cloud alone). The two paths then sample equally spread points, not
  the same ones (a model on a GPU, which computes its indices in torch, samples such a cloud differently from one on
  CPU).
  With ``tree`` (inference's ``sampling.fps: tree``, :class:`detector.stage1.sampling.SamplingConfig`) the numpy path
  takes the tree-based FPS on every cloud of at least ``2 ** TREE_FPS_HEIGHT`` points, also those up to
  :data:`EXACT_FPS_MAX_POINTS` that training samples with the loop.
* Ball query = the ``nsample`` nearest points within ``radius`` of the centre, nearest first; missing slots
  repeat the nearest one (the centre itself, since centres are sampled from the points).
* 3-NN weights are normalised inverse Euclidean distances ``1 / (d + 1e-8)``.

Levels: level 0 is the N input points; ``specs[l] = (npoint, radius, nsample)`` samples level ``l + 1``
(``npoint`` points) from level ``l`` and groups each new point's neighbours among level ``l``'s points.
"""

from __future__ import annotations

import fpsample
import numpy as np
import torch
from pykdtree.kdtree import KDTree

from detector.errors import DetectorError


#: Added to 3-NN distances before inverting them (metres).
INTERP_EPS = 1e-8
#: Clouds of up to this many points are sampled by fpsample's FPS loop from index 0: the cpu preset's 4096 points,
#: on which every shipped model trained and was measured, so their training runs and numbers stay as they were.
#: Larger clouds (denser inference, ``sampling.density``; the paper preset's 16384 points) take fpsample's
#: tree-based exact FPS (``bucket_fps_kdline``): 2.5 ms instead of 39 for 2048 of 8192 points (BENCHMARKS.md).
EXACT_FPS_MAX_POINTS = 4096
#: Height of that FPS's tree (fpsample suggests 3-5 for small clouds, 7-9 for large ones; 4 is the fastest of
#: 3-6 for 4096 and 8192 points here).
TREE_FPS_HEIGHT = 4

Spec = tuple[int, float, int]


def check_specs(num_points: int, specs: list[Spec]) -> None:
    """Raise DetectorError unless each level samples at most the points of the level before it.

    num_points: N input points; specs: [(npoint, radius, nsample), ...].
    """
    n = num_points
    for level, (npoint, radius, nsample) in enumerate(specs):
        if not (1 <= npoint <= n and radius > 0 and nsample >= 1):
            raise DetectorError(f"sampling level {level}: cannot take {npoint} points (radius {radius}, "
                                f"{nsample} neighbours) from {n} points")
        n = npoint


def fps_numpy(xyz: np.ndarray, npoint: int, tree: bool = False) -> np.ndarray:
    """Exact farthest point sampling (fpsample): from index 0 on clouds of up to :data:`EXACT_FPS_MAX_POINTS`
    points, from a point fpsample's tree picks on larger ones (the module's conventions), or with ``tree`` on every
    cloud of at least ``2 ** TREE_FPS_HEIGHT`` points (the tree's least; as well spread, about 10 times sooner on 4096
    points: BENCHMARKS.md).

    xyz: (N, 3) float32 metres. Returns (npoint,) int64 indices in sampling order.
    """
    if npoint == len(xyz) == 1:
        return np.zeros(1, np.int64)
    xyz = np.ascontiguousarray(xyz, dtype=np.float32)
    if (tree and len(xyz) >= 2 ** TREE_FPS_HEIGHT) or len(xyz) > EXACT_FPS_MAX_POINTS:
        return fpsample.bucket_fps_kdline_sampling(xyz, npoint, h=TREE_FPS_HEIGHT, start_idx=0).astype(np.int64)
    return fpsample.fps_sampling(xyz, npoint, start_idx=0).astype(np.int64)


def ball_query_numpy(xyz: np.ndarray, centres: np.ndarray, radius: float, nsample: int) -> np.ndarray:
    """The nsample nearest points within radius of each centre, nearest first, padded with the nearest.

    xyz: (N, 3) float32 metres; centres: (S, 3) float32 metres. Returns (S, nsample) int64 indices into xyz.
    """
    k = min(nsample, len(xyz))
    dist, idx = KDTree(np.ascontiguousarray(xyz, np.float32)).query(
        np.ascontiguousarray(centres, np.float32), k=k, distance_upper_bound=radius)
    idx = idx.reshape(len(centres), k).astype(np.int64)
    dist = dist.reshape(len(centres), k)
    idx = np.where(dist <= radius, idx, idx[:, :1])  # missing neighbours come back as N with distance inf
    if k < nsample:
        idx = np.concatenate([idx, np.repeat(idx[:, :1], nsample - k, axis=1)], axis=1)
    return idx


def inverse_distance_weights_numpy(dist: np.ndarray) -> np.ndarray:
    """Normalised inverse-distance weights along the last axis.

    dist: (..., 3) Euclidean distances, metres. Returns (..., 3) float32 summing to 1.
    """
    w = 1.0 / (dist.astype(np.float64) + INTERP_EPS)
    return (w / w.sum(-1, keepdims=True)).astype(np.float32)


def three_nn_numpy(unknown: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 3 nearest known points of each unknown point and their interpolation weights.

    unknown: (n, 3) float32 metres; known: (m, 3) float32 metres, m >= 1.
    Returns idx (n, 3) int64 into known (repeating the last neighbour when m < 3), w (n, 3) float32.
    """
    k = min(3, len(known))
    dist, idx = KDTree(np.ascontiguousarray(known, np.float32)).query(np.ascontiguousarray(unknown, np.float32), k=k)
    dist, idx = dist.reshape(len(unknown), k), idx.reshape(len(unknown), k).astype(np.int64)
    if k < 3:
        dist = np.concatenate([dist, np.repeat(dist[:, -1:], 3 - k, axis=1)], axis=1)
        idx = np.concatenate([idx, np.repeat(idx[:, -1:], 3 - k, axis=1)], axis=1)
    return idx, inverse_distance_weights_numpy(dist)


def precompute_indices(xyz: np.ndarray, specs: list[Spec], tree_fps: bool = False) -> dict[str, np.ndarray]:
    """All sampling / grouping / interpolation indices of one cloud (fast library path, for loader workers).

    xyz: (N, 3) float32 metres; specs: [(npoint, radius, nsample), ...] one per SA level; tree_fps: every level's
    FPS tree-based (:func:`fps_numpy`).
    Returns ``sample_l`` (npoint_l,) int64, ``group_l`` (npoint_l, nsample_l) int64 for l = 0..L-1 and
    ``interp_l_idx`` (n_l, 3) int64, ``interp_l_w`` (n_l, 3) float32 (3-NN of level l among level l+1) for
    l = 1..L-1. DetectorError when a level asks for more points than it has.
    """
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise DetectorError(f"xyz must have shape (N, 3), got {xyz.shape}")
    check_specs(len(xyz), specs)
    out: dict[str, np.ndarray] = {}
    levels = [np.ascontiguousarray(xyz, np.float32)]
    for level, (npoint, radius, nsample) in enumerate(specs):
        pts = levels[-1]
        sample = fps_numpy(pts, npoint, tree_fps)
        out[f"sample_{level}"] = sample
        out[f"group_{level}"] = ball_query_numpy(pts, pts[sample], radius, nsample)
        levels.append(pts[sample])
    for level in range(1, len(specs)):
        out[f"interp_{level}_idx"], out[f"interp_{level}_w"] = three_nn_numpy(levels[level], levels[level + 1])
    return out


def gather(values: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Rows of each batch element picked by index.

    values: (B, N, C); idx: (B, *S) int64 into N. Returns (B, *S, C).
    """
    b = torch.arange(values.shape[0], device=values.device).view(-1, *([1] * (idx.dim() - 1)))
    return values[b, idx]


def farthest_point_sample(xyz: torch.Tensor, npoint: int) -> torch.Tensor:
    """Exact farthest point sampling per batch element, starting at index 0.

    xyz: (B, N, 3) metres. Returns (B, npoint) int64 indices in sampling order.
    """
    bsz, n, _ = xyz.shape
    out = torch.zeros(bsz, npoint, dtype=torch.long, device=xyz.device)
    dist = torch.full((bsz, n), float("inf"), dtype=xyz.dtype, device=xyz.device)
    far = torch.zeros(bsz, dtype=torch.long, device=xyz.device)
    rows = torch.arange(bsz, device=xyz.device)
    for i in range(npoint):
        out[:, i] = far
        d = ((xyz - xyz[rows, far][:, None]) ** 2).sum(-1)
        dist = torch.minimum(dist, d)
        far = dist.argmax(-1)
    return out


def square_distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pairwise squared Euclidean distances by matrix product (fast; error ~1e-7 of the squared extent).

    a: (B, S, 3), b: (B, N, 3) metres. Returns (B, S, N) square metres.
    """
    centre = b.mean(dim=1, keepdim=True)  # centring keeps the cancellation error small
    a, b = a - centre, b - centre
    return ((a * a).sum(-1)[:, :, None] + (b * b).sum(-1)[:, None, :] - 2.0 * a @ b.transpose(1, 2)).clamp_min(0)


def knn(query: torch.Tensor, points: torch.Tensor, k: int, chunk_elems: int = 1 << 25
        ) -> tuple[torch.Tensor, torch.Tensor]:
    """The k nearest points of each query point, nearest first, with exact squared distances.

    query: (B, S, 3), points: (B, N, 3) metres, k <= N. Returns d2 (B, S, k) square metres and idx (B, S, k)
    int64. Candidates come from :func:`square_distances` in chunks of at most ``chunk_elems`` (B x chunk x N)
    entries; their distances are then recomputed exactly and re-sorted.
    """
    bsz, n, _ = points.shape
    step = max(1, chunk_elems // max(1, bsz * n))
    idx = torch.cat([torch.topk(square_distances(query[:, s:s + step], points), k, dim=-1, largest=False,
                                sorted=False).indices for s in range(0, query.shape[1], step)], dim=1)
    d2 = ((gather(points, idx) - query[:, :, None]) ** 2).sum(-1)
    d2, order = torch.sort(d2, dim=-1, stable=True)
    return d2, torch.gather(idx, -1, order)


def ball_query(xyz: torch.Tensor, centres: torch.Tensor, radius: float, nsample: int) -> torch.Tensor:
    """The nsample nearest points within radius of each centre, nearest first, padded with the nearest.

    xyz: (B, N, 3) metres; centres: (B, S, 3) metres. Returns (B, S, nsample) int64 indices into N.
    """
    k = min(nsample, xyz.shape[1])
    d2, idx = knn(centres, xyz, k)
    idx = torch.where(d2 <= radius * radius, idx, idx[..., :1])
    if k < nsample:
        idx = torch.cat([idx, idx[..., :1].expand(*idx.shape[:2], nsample - k)], dim=-1)
    return idx


def group(values: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Neighbour values of each centre (same as :func:`gather` with a (B, S, k) index).

    values: (B, N, C); idx: (B, S, k) int64. Returns (B, S, k, C).
    """
    return gather(values, idx)


def three_nn(unknown: torch.Tensor, known: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The 3 nearest known points of each unknown point and their inverse-distance weights.

    unknown: (B, n, 3), known: (B, m, 3) metres. Returns idx (B, n, 3) int64 into m (the last neighbour
    repeated when m < 3) and w (B, n, 3) summing to 1.
    """
    k = min(3, known.shape[1])
    d2, idx = knn(unknown, known, k)
    if k < 3:
        d2 = torch.cat([d2, d2[..., -1:].expand(*d2.shape[:2], 3 - k)], dim=-1)
        idx = torch.cat([idx, idx[..., -1:].expand(*idx.shape[:2], 3 - k)], dim=-1)
    w = 1.0 / (d2.clamp_min(0).sqrt() + INTERP_EPS)
    return idx, w / w.sum(-1, keepdim=True)


def three_interpolate(features: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Weighted sum of each point's 3 neighbours' features.

    features: (B, m, C); idx: (B, n, 3) int64 into m; w: (B, n, 3). Returns (B, n, C).
    """
    return (gather(features, idx) * w[..., None].to(features.dtype)).sum(-2)


@torch.no_grad()
def compute_indices_torch(xyz: torch.Tensor, specs: list[Spec]) -> dict[str, torch.Tensor]:
    """Batched pure-torch version of :func:`precompute_indices` (same keys, with a leading batch axis).

    xyz: (B, N, 3) metres. Returns ``sample_l`` (B, npoint_l), ``group_l`` (B, npoint_l, nsample_l),
    ``interp_l_idx`` (B, n_l, 3) int64 and ``interp_l_w`` (B, n_l, 3) float32.
    """
    check_specs(xyz.shape[1], specs)
    out: dict[str, torch.Tensor] = {}
    levels = [xyz]
    for level, (npoint, radius, nsample) in enumerate(specs):
        pts = levels[-1]
        sample = farthest_point_sample(pts, npoint)
        centres = gather(pts, sample)
        out[f"sample_{level}"] = sample
        out[f"group_{level}"] = ball_query(pts, centres, radius, nsample)
        levels.append(centres)
    for level in range(1, len(specs)):
        idx, w = three_nn(levels[level], levels[level + 1])
        out[f"interp_{level}_idx"], out[f"interp_{level}_w"] = idx, w.float()
    return out
