"""Stage-2 training items: each frame's usable instances as object-centred crops (:mod:`detector.stage2.crops`),
with an in-memory cache of the frames' crop regions, and their batching."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from detector.data.augment import input_normalisation
from detector.data.frames import FrameSource
from detector.stage2.crops import (CropFrame, PartTurns, crop_region, negative_crop, shape_only_symmetries,
                                   training_crop)


class CropDataset(FrameSource):
    """Stage-2 training items: every usable instance of a frame as an object-centred crop (:mod:`detector.stage2.crops`).

    ``dataset[(epoch, i)]`` is frame ``i``'s crops: ``features`` (c, n, 9), ``cls`` (c,) int64 class index
    (``class_ids[cls]`` is the object id), ``fg`` (c, n) float32, ``coords`` (c, S, n, 3) float32 model coordinates
    in diameters under each of the S symmetries of :func:`crop_symmetries` (for a crop that does not show its
    object's odd part, of :func:`part_turns`; padded to the most any object has),
    ``sym_mask`` (c, S) bool and ``frame`` (c,) int64. An instance is used when its object is in ``class_ids``, its
    visible fraction and point count reach the crop config's minimums and its crop holds enough points; with
    ``crop.negatives`` some instances also give a negative crop (:func:`detector.stage2.crops.negative_crop`: no
    foreground, its coordinates zero and only its first symmetry marked); c may be 0.
    Items are pure functions of (seed, epoch, frame). Batches join items with :func:`collate_crops`.

    cache_mb: each process keeps the :func:`detector.stage2.crops.crop_region` of the frames it reads, up to this many MB
    in all, and cuts later epochs' crops from memory: the same crops without reading and decompressing the frame
    again (with the whole label file read about 35 times in a default run, that is most of the data cost of a
    step). 0 = no cache.
    """

    def __init__(self, path: str | Path, crop_cfg, augment: bool = False, seed: int = 0,
                 class_ids: Sequence[int] | None = None, cache_mb: float = 0.0):
        super().__init__(path, seed, class_ids, augment)
        self.crop_cfg = crop_cfg
        self.normalisation = input_normalisation(crop_cfg.colour)  # the network input of every crop
        ids = self.objects["ids"]
        self.sym = crop_symmetries(self.objects, crop_cfg)
        self.diameters = {int(i): float(d) for i, d in zip(ids, self.objects["diameters"])}
        self.parts = part_turns(self.objects, self.sym) if crop_cfg.part_turns else {}
        self.max_sym = max(max(len(self.sym[c]), len(self.parts[c].symmetries) if c in self.parts else 0)
                           for c in self.class_ids)
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
            c = training_crop(frame, g, self.diameters[oid], self.sym[oid], cfg, rng, self.normalisation,
                              self.augment, self.parts.get(oid))
            if c is not None:
                crops.append((self.class_ids.index(oid), c))
            if cfg.negatives > 0 and rng.random() < cfg.negatives:
                c = negative_crop(frame, g, self.diameters[oid], self._crop_diameters, cfg, rng, self.normalisation,
                                  self.augment)
                if c is not None:
                    crops.append((self.class_ids.index(c["obj_id"]), {**c, "coords": np.zeros((1, n, 3), np.float32)}))
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


def crop_symmetries(objects: dict, crop_cfg) -> dict[int, np.ndarray]:
    """{object id: (S,4,4) float32}: the model-frame symmetries stage 2's coordinates are taught under (identity
    first). objects: a label file's object table as :func:`detector.data.frames.object_table_dict` gives it. Each
    object's own; for a stage 2 without colour input (``crop_cfg.colour`` "none", with ``crop_cfg.shape_turns``)
    also the turns that only its print breaks (:func:`detector.stage2.crops.shape_only_symmetries`), which
    geometry alone cannot tell apart."""
    ids = [int(i) for i in objects["ids"]]
    sym = {i: np.asarray(s, np.float32).reshape(-1, 4, 4) for i, s in zip(ids, objects["sym_transforms"])}
    turns = objects.get("shape_symmetries") or []
    if crop_cfg.colour == "none" and crop_cfg.shape_turns and len(turns) == len(ids):
        sym = {i: shape_only_symmetries(sym[i], t) for i, t in zip(ids, turns)}
    return sym


def part_turns(objects: dict, sym: dict[int, np.ndarray]) -> dict[int, PartTurns]:
    """{object id: :class:`detector.stage2.crops.PartTurns`} of the objects with a part symmetry in the object table
    (:func:`detector.data.frames.object_table_dict`; none in a label file written before part symmetries), built
    on the symmetries ``sym`` (:func:`crop_symmetries`) they are otherwise taught under."""
    ids = [int(i) for i in objects["ids"]]
    turns, odd = objects.get("part_symmetries") or [], objects.get("odd_points") or []
    if len(turns) != len(ids) or len(odd) != len(ids):
        return {}
    out = {}
    for i, t, p, d in zip(ids, turns, odd, objects["diameters"]):
        built = PartTurns.build(sym[i], t, p, d)
        if built is not None:
            out[i] = built
    return out


def collate_crops(items: Sequence[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Join crop items (see :class:`CropDataset`) along their first dimension."""
    return {k: torch.cat([it[k] for it in items]) for k in items[0]}
