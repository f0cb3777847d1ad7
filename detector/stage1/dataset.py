"""Stage 1's training and inference batches from ``argen label`` HDF5 files: point sampling, labels, augmentation,
indices.

Frames come through :class:`detector.data.frames.FrameSource`; every item is a pure function of ``(seed, epoch, frame
index)``, so data-loader workers, resumed runs and reruns see the same points. Neighbour indices for the network's
sampling stages are computed here (in the workers) with :func:`detector.stage1.ops.precompute_indices`.

Network input ``features`` (N, 9) float32 is ``[X, Y, Z, R', G', B', Nx, Ny, Nz]``: camera-frame metres
(unchanged: radii and offsets are metric), colour normalised as ``(rgb - rgb_mean) / rgb_std``
(:data:`detector.data.augment.NORMALISATION`, stored in checkpoints), unit normals.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from detector.data.augment import augment, input_normalisation, normalise_features
from detector.data.frames import FrameSource
from detector.data.plane import thin_plane_rows
from detector.errors import DetectorError
from detector.stage1.ops import precompute_indices


def sample_rows(num_rows: int, num_points: int, rng: np.random.Generator) -> np.ndarray:
    """Rows to feed the network: random without replacement when enough, else all rows then repeats.

    Returns: (num_points,) int64 indices into ``range(num_rows)``, sorted within the distinct part.
    """
    if num_rows <= 0:
        raise DetectorError("a frame has no points")
    if num_rows >= num_points:
        return np.sort(rng.choice(num_rows, num_points, replace=False)).astype(np.int64)
    extra = rng.choice(num_rows, num_points - num_rows, replace=True)
    return np.concatenate([np.arange(num_rows), extra]).astype(np.int64)


def frame_rows(features: np.ndarray, num_points: int, rng: np.random.Generator, plane_keep: float = 1.0
               ) -> np.ndarray:
    """The rows of a frame that stage 1 sees: :func:`sample_rows` over the frame's points after all but a
    ``plane_keep`` share of its dominant plane's points are set aside (:func:`detector.data.plane.thin_plane_rows`;
    1 keeps them all and draws exactly as :func:`sample_rows` alone).

    features: (N, 9) (only the xyz columns, metres, are read). Returns (num_points,) int64 rows of ``features``.
    """
    pool = thin_plane_rows(np.asarray(features)[:, :3], num_points, plane_keep, rng)
    return pool[sample_rows(len(pool), num_points, rng)]


def class_index(semantic: np.ndarray, class_ids: Sequence[int]) -> np.ndarray:
    """Class index of each point: 0 for background or an object not in ``class_ids``, else 1 + its rank.

    semantic: (N,) int object ids (0 = background); class_ids: sorted object ids. Returns (N,) int64.
    """
    ids = np.asarray(class_ids, dtype=np.int64)
    pos = np.searchsorted(ids, semantic)
    found = (pos < len(ids)) & (ids[np.minimum(pos, len(ids) - 1)] == semantic)
    return np.where(found, pos + 1, 0).astype(np.int64)


def sampling_indices(xyz: np.ndarray, specs: list[tuple[int, float, int]], tree_fps: bool = False
                     ) -> dict[str, torch.Tensor]:
    """The network's sampling / neighbour indices of one cloud as tensors
    (:func:`detector.stage1.ops.precompute_indices`).

    xyz: (N, 3) float32 metres; specs: the model config's ``sampling_specs()``; tree_fps: every level's FPS
    tree-based.
    """
    out = precompute_indices(np.ascontiguousarray(xyz, dtype=np.float32), specs, tree_fps)
    return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in out.items()}


class PointDataset(FrameSource):
    """Per-frame training items from a label file: ``num_points`` sampled points, labels, sampling indices.

    ``dataset[i]`` is frame ``i`` of epoch 0; ``dataset[(epoch, i)]`` draws the sample of another epoch.
    An item is a dict of tensors: ``features`` (N, 9) float32 (normalised network input), ``cls`` (N,)
    int64 (0 = background, c = ``class_ids[c - 1]``), ``instance`` (N,) int64 (-1 = background),
    ``control_points`` (N, 9, 3) float32 metres, the :func:`detector.stage1.ops.precompute_indices` arrays and
    ``frame`` (int). The label file is opened lazily in each process (never pickled into workers).
    ``precompute=False`` leaves the indices out (the model then computes them on its device); ``colour`` is the
    colour input (:func:`detector.data.augment.augment`'s mode; "none" zeroes the colour channels).
    """

    def __init__(self, path: str | Path, model_cfg, num_points: int, augment: bool = False, seed: int = 0,
                 class_ids: Sequence[int] | None = None, precompute: bool = True, colour: str = "light",
                 plane_keep: float = 1.0):
        self.model_cfg = model_cfg
        self.plane_keep = float(plane_keep)
        self.colour = colour
        self.normalisation = input_normalisation(colour)
        self.specs = list(model_cfg.sampling_specs())
        self.num_points = int(num_points)
        self.precompute = bool(precompute)
        if self.specs and self.num_points < self.specs[0][0]:
            raise DetectorError(f"num_points {self.num_points} is below the first sampling stage's "
                                f"{self.specs[0][0]} keypoints")
        super().__init__(path, seed, class_ids, augment)

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, torch.Tensor]:
        frame, rng, index = self.read(key)
        rows = frame_rows(frame.features, self.num_points, rng, self.plane_keep)
        feats = np.asarray(frame.features, dtype=np.float32)[rows]
        cps = np.asarray(frame.control_points, dtype=np.float32)[rows]
        cls = class_index(np.asarray(frame.semantic)[rows], self.class_ids)
        instance = np.where(cls > 0, np.asarray(frame.instance)[rows], -1).astype(np.int64)
        cps = np.where((cls > 0)[:, None, None], cps, 0.0).astype(np.float32)
        if self.augment:
            feats, cps = augment(feats, cps, rng, self.colour)
        item = sampling_indices(feats[:, :3], self.specs) if self.precompute else {}
        item.update(features=torch.from_numpy(normalise_features(feats, self.normalisation)), cls=torch.from_numpy(cls),
                    instance=torch.from_numpy(instance), control_points=torch.from_numpy(cps),
                    frame=torch.tensor(index, dtype=torch.int64))
        return item


def inference_batch(features: np.ndarray, model_cfg, num_points: int, seed: int | Sequence[int] = 0,
                    normalisation: dict[str, float] | None = None, precompute: bool = True,
                    plane_keep: float = 1.0, tree_fps: bool = False) -> dict[str, torch.Tensor]:
    """A batch of one frame for prediction: the same sampling as training, without augmentation (with
    ``tree_fps``, every level's FPS tree-based: as well spread points from another first point).

    features: (N, 9) float32 [X, Y, Z, R, G, B, Nx, Ny, Nz], metres and colour in [0, 1]; seed: of the draw
    (``numpy.random.default_rng``'s: an int or a sequence of ints).
    Returns ``features`` (1, num_points, 9), the sampling indices (each with a batch dimension) and
    ``point_index`` (num_points,) int64: the input row of each network point. ``precompute=False`` leaves
    the indices out (for a model that computes them on the GPU); ``plane_keep``: as the model was trained
    (:func:`frame_rows`).
    """
    feats = np.asarray(features, dtype=np.float32)
    if feats.ndim != 2 or feats.shape[1] != 9:
        raise DetectorError(f"features must have shape (N, 9), got {feats.shape}")
    rows = frame_rows(feats, int(num_points), np.random.default_rng(seed), plane_keep)
    sel = feats[rows]
    specs = list(model_cfg.sampling_specs())
    batch = {k: v[None] for k, v in sampling_indices(sel[:, :3], specs, tree_fps).items()} if precompute else {}
    batch["features"] = torch.from_numpy(normalise_features(sel, normalisation))[None]
    batch["point_index"] = torch.from_numpy(rows)
    return batch
