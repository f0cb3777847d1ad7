"""A label file's frames for the datasets of both stages, read only through :mod:`argen.h5`: opening with one-line
errors, shape checks, a lazily opened per-process handle, the object table as plain lists, and each item's
generator from (seed, epoch, frame index), so loader workers, resumed runs and reruns see the same items."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from argen.h5 import LabelFile
from detector.errors import DetectorError, argen_errors


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
    """The frames of one label file, or of several label files of the same objects one after the other (``path`` a
    list: e.g. a capture without distractors and one among them for stage 1), for a Dataset: opened lazily in each
    process (never pickled into workers), the object table, the classes to learn (``class_ids``, sorted object ids),
    the working volume its points were taken from (``max_depth``: metres along z, None when the files do not say)
    and the per-item generator. Item ``i`` is frame ``i`` of the files taken in order; its generator depends on
    ``i``, so a file's frames draw other samples in another position of the list."""

    def __init__(self, path: str | Path | Sequence[str | Path], seed: int = 0,
                 class_ids: Sequence[int] | None = None, augment: bool = False):
        self.paths = [Path(p) for p in ([path] if isinstance(path, (str, Path)) else path)]
        if not self.paths:
            raise DetectorError("no label file given")
        self.path = self.paths[0]
        self.seed = int(seed)
        self.augment = bool(augment)
        self._files, self._pid = None, None
        counts, depths = [], []
        for k, p in enumerate(self.paths):
            lf = open_label_file(p)
            try:
                with argen_errors():
                    counts.append(int(lf.num_frames))
                    objects = object_table_dict(lf.objects)
                    depth = lf.attrs.get("max_depth")
                    depths.append(float(depth) if depth is not None and float(depth) > 0 else None)
                    if counts[-1] == 0:
                        raise DetectorError(f"{p}: the label file has no frames")
                    check_frame(lf.frame(0), p, 0)  # one frame checks the shared datasets' shapes and dtypes
            finally:
                lf.close()
            if k == 0:
                self.objects = objects
            else:
                _check_same_table(self.objects, objects, self.paths[0], p)
        if len(set(depths)) > 1:
            raise DetectorError(f"the label files were labelled with different working volumes (--max-depth "
                                f"{', '.join(map(str, depths))} m for {', '.join(map(str, self.paths))}): label "
                                "them with one")
        self.max_depth = depths[0]
        self.starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)  # (F+1,) first item of each file
        self.num_frames = int(self.starts[-1])
        ids = sorted(int(i) for i in (self.objects["ids"] if class_ids is None else class_ids))
        if not ids:
            raise DetectorError(f"{self.path}: no object classes to train on")
        self.class_ids = ids

    def __len__(self) -> int:
        return self.num_frames

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_files"], state["_pid"] = None, None
        return state

    def _label_file(self, k: int = 0):
        if self._files is None or self._pid != os.getpid():
            self._files = [None] * len(self.paths)
            self._pid = os.getpid()
        if self._files[k] is None:
            self._files[k] = open_label_file(self.paths[k])
        return self._files[k]

    def close(self) -> None:
        """Close this process's handles on the label files (reopened on the next item)."""
        if self._files is not None and self._pid == os.getpid():
            for f in self._files:
                if f is not None:
                    f.close()
        self._files, self._pid = None, None

    def rng(self, epoch: int, index: int) -> np.random.Generator:
        """The generator of one item, from (seed, epoch, item index)."""
        return np.random.default_rng([self.seed, int(epoch), int(index)])

    def read(self, key: int | tuple[int, int]):
        """(frame labels, generator, item index) of item ``key`` = index or (epoch, index); checked."""
        epoch, index = key if isinstance(key, tuple) else (0, key)
        index = int(index)
        if not 0 <= index < self.num_frames:
            raise IndexError(f"frame {index} out of range (0..{self.num_frames - 1})")
        k = int(np.searchsorted(self.starts, index, side="right")) - 1
        local = index - int(self.starts[k])
        with argen_errors():
            frame = self._label_file(k).frame(local)
        check_frame(frame, self.paths[k], local)
        return frame, self.rng(epoch, index), index


def _check_same_table(a: dict, b: dict, path_a: Path, path_b: Path) -> None:
    """Raise a one-line DetectorError unless two label files' object tables (:func:`object_table_dict`) hold the
    same objects: ids, names, diameters and box control points."""
    same = (a["ids"] == b["ids"] and a["names"] == b["names"]
            and np.allclose(a["diameters"], b["diameters"], atol=1e-6)
            and np.allclose(a["control_points"], b["control_points"], atol=1e-6))
    if not same:
        raise DetectorError(f"{path_b} holds other objects than {path_a} ({b['names']} against {a['names']}): "
                            "label files trained on together must be labelled with the same models")


def object_table_dict(objects) -> dict:
    """The label file's object table as plain lists (for checkpoints): ids, names, diameters, symmetric,
    control_points (M, 9, 3) metres, model_points (M, P, 3) metres, sym_transforms per object (S, 4, 4),
    shape_symmetries per object (T, 4, 4), texture_points (N, 3) metres and texture_colours (N, 3) 0-255 per
    object, part_symmetries per object (P, 4, 4) and odd_points (K, 3) metres per object, surface_points (S, 3)
    metres and surface_normals (S, 3) per object (empty lists for a label file without them)."""
    return {
        "ids": [int(i) for i in objects.ids],
        "names": [str(n) for n in objects.names],
        "diameters": [float(d) for d in objects.diameters],
        "symmetric": [bool(s) for s in objects.symmetric],
        "control_points": np.asarray(objects.control_points, dtype=np.float32).tolist(),
        "model_points": np.asarray(objects.model_points, dtype=np.float32).tolist(),
        "sym_transforms": [np.asarray(s, dtype=np.float32).tolist() for s in objects.sym_transforms],
        "shape_symmetries": [np.asarray(s, dtype=np.float32).tolist() for s in objects.shape_symmetries],
        "texture_points": [np.asarray(p, dtype=np.float32).tolist() for p in objects.texture_points],
        "texture_colours": [np.asarray(c, dtype=np.uint8).tolist() for c in objects.texture_colours],
        "part_symmetries": [np.asarray(s, dtype=np.float32).tolist() for s in objects.part_symmetries],
        "odd_points": [np.asarray(p, dtype=np.float32).tolist() for p in objects.odd_points],
        "surface_points": [np.asarray(p, dtype=np.float32).tolist() for p in objects.surface_points],
        "surface_normals": [np.asarray(n, dtype=np.float32).tolist() for n in objects.surface_normals],
    }
