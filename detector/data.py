"""Training and inference batches from ``argen label`` HDF5 files: point sampling, labels, augmentation, indices.

The only detector module that reads label files, and only through :mod:`argen.h5`. Every item is a pure
function of ``(seed, epoch, frame index)``, so data-loader workers, resumed runs and reruns see the same
points. Neighbour indices for the network's sampling stages are computed here (in the workers) with
:func:`detector.ops.precompute_indices`.

Network input ``features`` (N, 9) float32 is ``[X, Y, Z, R', G', B', Nx, Ny, Nz]``: camera-frame metres
(unchanged: radii and offsets are metric), colour normalised as ``(rgb - rgb_mean) / rgb_std``
(:data:`NORMALISATION`, stored in checkpoints), unit normals.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import torch

from argen.h5 import LabelFile
from detector.crops import CropFrame, camera_colour, crop_region, normalised_colour, training_crop
from detector.errors import DetectorError, argen_errors
from detector.ops import precompute_indices

#: Colour normalisation of the network input; the label file stores colour in [0, 1].
NORMALISATION: dict[str, float] = {"rgb_mean": 0.5, "rgb_std": 0.25}


def input_normalisation(colour: str) -> dict:
    """The input normalisation a stage trained with colour mode ``colour`` (``detector.crops.COLOUR_MODES``) keeps in
    its checkpoint: :data:`NORMALISATION`, plus ``"colour": "none"`` for a network without colour input (its colour
    channels are zero in training and at inference)."""
    return {**NORMALISATION, "colour": "none"} if colour == "none" else dict(NORMALISATION)

#: Augmentation strengths (metres, radians, colour units in [0, 1]).
JITTER_SIGMA = 0.002
JITTER_CLIP = 0.005
ROTATION_MAX = np.deg2rad(15.0)
BRIGHTNESS = 0.15
COLOUR_SIGMA = 0.02


# ------------------------------------------------------------------------------------------------- helpers


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


def class_index(semantic: np.ndarray, class_ids: Sequence[int]) -> np.ndarray:
    """Class index of each point: 0 for background or an object not in ``class_ids``, else 1 + its rank.

    semantic: (N,) int object ids (0 = background); class_ids: sorted object ids. Returns (N,) int64.
    """
    ids = np.asarray(class_ids, dtype=np.int64)
    pos = np.searchsorted(ids, semantic)
    found = (pos < len(ids)) & (ids[np.minimum(pos, len(ids) - 1)] == semantic)
    return np.where(found, pos + 1, 0).astype(np.int64)


def normalise_features(features: np.ndarray, normalisation: dict[str, float] | None = None) -> np.ndarray:
    """Network input from label-file features: colour centred and scaled, xyz and normals unchanged.

    features: (N, 9) float32 [X, Y, Z, R, G, B, Nx, Ny, Nz] with colour in [0, 1]. Returns (N, 9) float32.
    """
    norm = NORMALISATION if normalisation is None else normalisation
    out = np.array(features, dtype=np.float32, copy=True)
    out[:, 3:6] = normalised_colour(out[:, 3:6], norm)
    return out


def rot_z(angle: float) -> np.ndarray:
    """Rotation about the camera's optical (z) axis by ``angle`` radians: (3, 3) float32."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float32)


def augment(features: np.ndarray, control_points: np.ndarray, rng: np.random.Generator, colour: str = "light"
            ) -> tuple[np.ndarray, np.ndarray]:
    """Light augmentation: a small roll about the camera axis (points, normals and labels alike), xyz jitter,
    and a colour change: ``colour`` "light" is a brightness gain of +-15 % and colour noise, "camera" the whole
    frame's colours as another camera would give them (:func:`detector.crops.camera_colour`: exposure, white
    balance, gamma, sometimes grey or none), "none" leaves colour as it is (the network does not see it).

    features: (N, 9) float32, colour in [0, 1]; control_points: (N, 9, 3) float32 metres (zeros = background).
    Returns new arrays of the same shapes; background control points stay zero.
    """
    R = rot_z(rng.uniform(-ROTATION_MAX, ROTATION_MAX))
    out = np.array(features, dtype=np.float32, copy=True)
    out[:, 0:3] = out[:, 0:3] @ R.T
    out[:, 6:9] = out[:, 6:9] @ R.T
    cps = (control_points @ R.T).astype(np.float32)
    jitter = np.clip(rng.normal(0.0, JITTER_SIGMA, (len(out), 3)), -JITTER_CLIP, JITTER_CLIP)
    out[:, 0:3] += jitter.astype(np.float32)
    if colour == "camera":
        out[:, 3:6] = camera_colour(out[:, 3:6], rng)
    elif colour == "light":
        gain = rng.uniform(1.0 - BRIGHTNESS, 1.0 + BRIGHTNESS)
        out[:, 3:6] = np.clip(out[:, 3:6] * gain + rng.normal(0.0, COLOUR_SIGMA, (len(out), 3)), 0.0, 1.0)
    return out, cps


def sampling_indices(xyz: np.ndarray, specs: list[tuple[int, float, int]]) -> dict[str, torch.Tensor]:
    """The network's sampling / neighbour indices of one cloud as tensors (:func:`detector.ops.precompute_indices`).

    xyz: (N, 3) float32 metres; specs: the model config's ``sampling_specs()``.
    """
    out = precompute_indices(np.ascontiguousarray(xyz, dtype=np.float32), specs)
    return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in out.items()}


# ------------------------------------------------------------------------------------------------- dataset


def open_label_file(path: str | Path):
    """Open a label file through :mod:`argen.h5`; a missing or malformed file is a :class:`DetectorError`."""

    with argen_errors():
        return LabelFile(Path(path))


def check_frame(frame, path: Path, i: int) -> None:
    """Raise a one-line :class:`DetectorError` when a frame's arrays have the wrong shape or dtype."""
    n = len(frame.features)
    checks = [
        ("points/features", frame.features, (n, 9), np.floating),
        ("points/semantic", frame.semantic, (n,), np.integer),
        ("points/instance", frame.instance, (n,), np.integer),
        ("control points", frame.control_points, (n, 9, 3), np.floating),
    ]
    for name, arr, shape, kind in checks:
        arr = np.asarray(arr)
        if arr.shape != shape or not np.issubdtype(arr.dtype, kind):
            want = "float" if kind is np.floating else "integer"
            raise DetectorError(f"{path}: frame {i}: {name} has shape {arr.shape} and dtype {arr.dtype}, "
                                f"expected {shape} {want}")
    if n == 0:
        raise DetectorError(f"{path}: frame {i} has no points")


class FrameSource(torch.utils.data.Dataset):
    """A label file's frames for a Dataset: opened lazily in each process (never pickled into workers), the
    object table, the classes to learn (``class_ids``, sorted object ids) and the per-item generator."""

    def __init__(self, path: str | Path, seed: int = 0, class_ids: Sequence[int] | None = None,
                 augment: bool = False):
        self.path = Path(path)
        self.seed = int(seed)
        self.augment = bool(augment)
        self._file = None
        self._pid = None
        lf = open_label_file(self.path)
        try:
            with argen_errors():
                self.num_frames = int(lf.num_frames)
                self.objects = object_table_dict(lf.objects)
                if self.num_frames == 0:
                    raise DetectorError(f"{self.path}: the label file has no frames")
                check_frame(lf.frame(0), self.path, 0)  # one frame checks the shared datasets' shapes and dtypes
        finally:
            lf.close()
        ids = sorted(int(i) for i in (self.objects["ids"] if class_ids is None else class_ids))
        if not ids:
            raise DetectorError(f"{self.path}: no object classes to train on")
        self.class_ids = ids

    def __len__(self) -> int:
        return self.num_frames

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_file"], state["_pid"] = None, None
        return state

    def _label_file(self):
        if self._file is None or self._pid != os.getpid():
            self._file = open_label_file(self.path)
            self._pid = os.getpid()
        return self._file

    def close(self) -> None:
        """Close this process's handle on the label file (reopened on the next item)."""
        if self._file is not None and self._pid == os.getpid():
            self._file.close()
        self._file, self._pid = None, None

    def rng(self, epoch: int, index: int) -> np.random.Generator:
        """The generator of one item, from (seed, epoch, frame index)."""
        return np.random.default_rng([self.seed, int(epoch), int(index)])

    def read(self, key: int | tuple[int, int]):
        """(frame labels, generator, frame index) of item ``key`` = index or (epoch, index); checked."""
        epoch, index = key if isinstance(key, tuple) else (0, key)
        index = int(index)
        if not 0 <= index < self.num_frames:
            raise IndexError(f"frame {index} out of range (0..{self.num_frames - 1})")
        with argen_errors():
            frame = self._label_file().frame(index)
        check_frame(frame, self.path, index)
        return frame, self.rng(epoch, index), index


class PointDataset(FrameSource):
    """Per-frame training items from a label file: ``num_points`` sampled points, labels, sampling indices.

    ``dataset[i]`` is frame ``i`` of epoch 0; ``dataset[(epoch, i)]`` draws the sample of another epoch.
    An item is a dict of tensors: ``features`` (N, 9) float32 (normalised network input), ``cls`` (N,)
    int64 (0 = background, c = ``class_ids[c - 1]``), ``instance`` (N,) int64 (-1 = background),
    ``control_points`` (N, 9, 3) float32 metres, the :func:`detector.ops.precompute_indices` arrays and
    ``frame`` (int). The label file is opened lazily in each process (never pickled into workers).
    ``precompute=False`` leaves the indices out (the model then computes them on its device); ``colour`` is the
    colour augmentation of :func:`augment`.
    """

    def __init__(self, path: str | Path, model_cfg, num_points: int, augment: bool = False, seed: int = 0,
                 class_ids: Sequence[int] | None = None, precompute: bool = True, colour: str = "light"):
        self.model_cfg = model_cfg
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
        rows = sample_rows(len(frame.features), self.num_points, rng)
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


def object_table_dict(objects) -> dict:
    """The label file's object table as plain lists (for checkpoints): ids, names, diameters, symmetric,
    control_points (M, 9, 3) metres, model_points (M, P, 3) metres, sym_transforms per object (S, 4, 4)."""
    return {
        "ids": [int(i) for i in objects.ids],
        "names": [str(n) for n in objects.names],
        "diameters": [float(d) for d in objects.diameters],
        "symmetric": [bool(s) for s in objects.symmetric],
        "control_points": np.asarray(objects.control_points, dtype=np.float32).tolist(),
        "model_points": np.asarray(objects.model_points, dtype=np.float32).tolist(),
        "sym_transforms": [np.asarray(s, dtype=np.float32).tolist() for s in objects.sym_transforms],
    }


def collate(items: Sequence[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack a list of items into a batch: every key gains a leading batch dimension."""
    return {k: torch.stack([it[k] for it in items]) for k in items[0]}


def rank_share(batch_size: int, rank: int, world_size: int) -> slice:
    """The part of a global batch of ``batch_size`` keys that process ``rank`` of ``world_size`` takes.

    Returns a slice of ``batch_size // world_size`` consecutive positions; a batch size that the world
    size does not divide is a :class:`DetectorError`.
    """
    if world_size < 1 or not 0 <= rank < world_size:
        raise ValueError(f"rank {rank} is not in a world of {world_size}")
    if batch_size % world_size:
        raise DetectorError(f"batch_size {batch_size} is not divisible by the {world_size} distributed processes; "
                            f"choose a multiple of {world_size}")
    per = batch_size // world_size
    return slice(rank * per, (rank + 1) * per)


class StreamBatchSampler(torch.utils.data.Sampler):
    """An endless stream of batches of ``(epoch, frame)`` keys, starting at batch ``start``.

    Epoch ``e`` visits the frames in the order ``default_rng([seed, e]).permutation(num_frames)``; batches
    are consecutive runs of ``batch_size`` keys of this stream (they may span an epoch boundary), so batch
    ``b`` is the same whether the run started at 0 or was resumed at ``b``. With ``world_size`` > 1 (DDP)
    process ``rank`` yields its :func:`rank_share` of each global batch: together the processes see the
    keys one process would.
    """

    def __init__(self, num_frames: int, batch_size: int, seed: int, start: int = 0, rank: int = 0,
                 world_size: int = 1):
        self.num_frames, self.batch_size, self.seed, self.start = num_frames, batch_size, seed, start
        self.share = rank_share(batch_size, rank, world_size)

    def keys(self, first: int, count: int) -> list[tuple[int, int]]:
        """Keys at stream positions ``first .. first + count - 1``."""
        out, pos = [], first
        while len(out) < count:
            epoch, j = divmod(pos, self.num_frames)
            perm = np.random.default_rng([self.seed, epoch]).permutation(self.num_frames)
            take = min(count - len(out), self.num_frames - j)
            out += [(epoch, int(i)) for i in perm[j:j + take]]
            pos += take
        return out

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        b = self.start
        while True:
            yield self.keys(b * self.batch_size + self.share.start, self.share.stop - self.share.start)
            b += 1

    def __len__(self) -> int:  # endless; a large number keeps DataLoader happy
        return 2**62


def inference_batch(features: np.ndarray, model_cfg, num_points: int, seed: int = 0,
                    normalisation: dict[str, float] | None = None, precompute: bool = True) -> dict[str, torch.Tensor]:
    """A batch of one frame for prediction: the same sampling as training, without augmentation.

    features: (N, 9) float32 [X, Y, Z, R, G, B, Nx, Ny, Nz], metres and colour in [0, 1].
    Returns ``features`` (1, num_points, 9), the sampling indices (each with a batch dimension) and
    ``point_index`` (num_points,) int64: the input row of each network point. ``precompute=False`` leaves
    the indices out (for a model that computes them on the GPU).
    """
    feats = np.asarray(features, dtype=np.float32)
    if feats.ndim != 2 or feats.shape[1] != 9:
        raise DetectorError(f"features must have shape (N, 9), got {feats.shape}")
    rows = sample_rows(len(feats), int(num_points), np.random.default_rng(seed))
    sel = feats[rows]
    specs = list(model_cfg.sampling_specs())
    batch = {k: v[None] for k, v in sampling_indices(sel[:, :3], specs).items()} if precompute else {}
    batch["features"] = torch.from_numpy(normalise_features(sel, normalisation))[None]
    batch["point_index"] = torch.from_numpy(rows)
    return batch


# ------------------------------------------------------------------------------------------------- stage 2


class CropDataset(FrameSource):
    """Stage-2 training items: every usable instance of a frame as an object-centred crop (:mod:`detector.crops`).

    ``dataset[(epoch, i)]`` is frame ``i``'s crops: ``features`` (c, n, 9), ``cls`` (c,) int64 class index
    (``class_ids[cls]`` is the object id), ``fg`` (c, n) float32, ``coords`` (c, S, n, 3) float32 model coordinates
    in diameters under each of the S symmetries (padded to the most any object has), ``sym_mask`` (c, S) bool and
    ``frame`` (c,) int64. An instance is used when its object is in ``class_ids``, its visible fraction and point
    count reach the crop config's minimums and its crop holds enough points; c may be 0.
    Items are pure functions of (seed, epoch, frame). Batches join items with :func:`collate_crops`.

    cache_mb: each process keeps the :func:`detector.crops.crop_region` of the frames it reads, up to this many MB
    in all, and cuts later epochs' crops from memory: the same crops without reading and decompressing the frame
    again (with the whole label file read about 35 times in a default run, that is most of the data cost of a
    step). 0 = no cache.
    """

    def __init__(self, path: str | Path, crop_cfg, augment: bool = False, seed: int = 0,
                 class_ids: Sequence[int] | None = None, cache_mb: float = 0.0):
        super().__init__(path, seed, class_ids, augment)
        self.crop_cfg = crop_cfg
        ids = self.objects["ids"]
        self.sym = {int(i): np.asarray(s, np.float32) for i, s in zip(ids, self.objects["sym_transforms"])}
        self.diameters = {int(i): float(d) for i, d in zip(ids, self.objects["diameters"])}
        self.max_sym = max(len(self.sym[c]) for c in self.class_ids)
        self._crop_diameters = {c: self.diameters[c] for c in self.class_ids}  # the objects whose crops are cut
        self.cache_bytes = int(max(cache_mb, 0.0) * 2 ** 20)
        self._cache: dict[int, CropFrame] = {}
        self._cached = 0

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state["_cache"], state["_cached"] = {}, 0  # each worker fills its own
        return state

    def _frame(self, key: int | tuple[int, int]):
        """(crop region, generator, frame index) of item ``key``, from the cache when it holds the frame."""
        epoch, index = key if isinstance(key, tuple) else (0, key)
        region = self._cache.get(int(index))
        if region is not None:
            return region, self.rng(epoch, index), int(index)
        frame, rng, index = self.read(key)
        region = crop_region(frame, self._crop_diameters, self.crop_cfg)
        if self._cached + region.nbytes <= self.cache_bytes:
            self._cache[index] = region
            self._cached += region.nbytes
        return region, rng, index

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, torch.Tensor]:
        frame, rng, index = self._frame(key)
        cfg, n, S = self.crop_cfg, self.crop_cfg.num_points, self.max_sym
        inst = frame.instances
        crops = []
        for g in range(len(inst)):
            oid = int(inst.obj_id[g])
            if oid not in self.class_ids or inst.visib_fract[g] < cfg.min_visib or inst.num_points[g] < cfg.min_object_points:
                continue
            c = training_crop(frame, g, self.diameters[oid], self.sym[oid], cfg, rng,
                                  input_normalisation(cfg.colour), self.augment)
            if c is not None:
                crops.append((self.class_ids.index(oid), c))
        feats = np.zeros((len(crops), n, 9), np.float32)
        fg = np.zeros((len(crops), n), np.float32)
        coords = np.zeros((len(crops), S, n, 3), np.float32)
        mask = np.zeros((len(crops), S), bool)
        for k, (_, c) in enumerate(crops):
            feats[k], fg[k] = c["features"], c["fg"]
            s = len(c["coords"])
            coords[k, :s], mask[k, :s] = c["coords"], True
        return {"features": torch.from_numpy(feats), "cls": torch.tensor([c for c, _ in crops], dtype=torch.int64),
                "fg": torch.from_numpy(fg), "coords": torch.from_numpy(coords), "sym_mask": torch.from_numpy(mask),
                "frame": torch.full((len(crops),), index, dtype=torch.int64)}


def collate_crops(items: Sequence[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Join crop items (see :class:`CropDataset`) along their first dimension."""
    return {k: torch.cat([it[k] for it in items]) for k in items[0]}
