"""The HDF5 label file (schema v1, docs/hdf5-schema.md): the only module that knows its layout.

Reader: :class:`LabelFile` (read-only, cheap to open: it loads the object table and the per-frame
offsets, and reads a frame's rows only when asked). Writer: :class:`LabelWriter` streams frames into
resizable chunked datasets of a temporary file beside the target and renames it onto the target on
:meth:`LabelWriter.close`, so a reader never sees a half-written file. Everything is metres.

A LabelFile holds an open h5py handle: do not pickle it into DataLoader workers, open one lazily in
each worker (pickling raises TypeError).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from argen.errors import ArgenError
from argen.fileio import atomic_path

SCHEMA_VERSION = 1
POINT_CHUNK = 16384  # rows per HDF5 chunk of the points/* datasets
INSTANCE_CHUNK = 1024
COMPRESSION = {None: {}, "lzf": dict(compression="lzf", shuffle=True),
               "gzip": dict(compression="gzip", compression_opts=4, shuffle=True)}

# name -> (trailing shape, dtype) of the ragged datasets
POINT_FIELDS = {
    "features": ((9,), np.float32),
    "pixel": ((2,), np.int32),
    "semantic": ((), np.int32),
    "instance": ((), np.int32),
}
INSTANCE_FIELDS = {
    "obj_id": ((), np.int32),
    "gt_index": ((), np.int32),
    "R": ((3, 3), np.float32),
    "t": ((3,), np.float32),
    "control_points": ((9, 3), np.float32),
    "visib_fract": ((), np.float32),
    "num_points": ((), np.int32),
}
FRAME_FIELDS = {
    "scene_id": ((), np.int32),
    "im_id": ((), np.int32),
    "cam_K": ((3, 3), np.float32),
    "image_size": ((2,), np.int32),
}
OBJECT_FIELDS = ("ids", "names", "diameters", "symmetric", "corners", "control_points", "model_points",
                 "sym_offsets", "sym_transforms")
ROOT_ATTRS = ("schema_version", "created_by", "source_dataset", "source_split", "source_argen_json",
              "max_points", "max_depth", "subsampling", "num_frames")


# ---------------------------------------------------------------------------------------- tables


@dataclass
class ObjectTable:
    """The label file's objects (M, sorted by id), metres, model frame.

    ids: (M,) int32; names: M str; diameters: (M,) float32; symmetric: (M,) bool;
    corners: (M,8,3) float32; control_points: (M,9,3) float32 (corners then centre);
    model_points: (M,P,3) float32 surface sample; sym_transforms: per object (S_m,4,4) float32, identity first.
    Optional (empty lists: none for any object, as in files written before they existed): shape_symmetries: per
    object (T_m,4,4) float32, the turns that map its shape onto itself but that its texture breaks
    (:func:`argen.models.texture.shape_symmetries`); texture_points: per object (N_m,3) float32 surface sample and
    texture_colours: per object (N_m,3) uint8 RGB its colours there (N_m = 0: the object has no such turns, or no
    print to tell them apart); part_symmetries: per object (P_m,4,4) float32, the turns about an axis that map all
    of its surface but an odd part (a mug's handle) onto itself, and odd_points: per object (K_m,3) float32 surface
    samples of that part (:func:`argen.models.symmetry.find_part_symmetry`; P_m = K_m = 0: it has none);
    surface_points and surface_normals: per object (S_m,3) float32 surface samples and their outward unit normals
    (``argen.label.SURFACE_POINTS`` of them).
    """

    ids: np.ndarray
    names: list[str]
    diameters: np.ndarray
    symmetric: np.ndarray
    corners: np.ndarray
    control_points: np.ndarray
    model_points: np.ndarray
    sym_transforms: list[np.ndarray]
    shape_symmetries: list[np.ndarray] = field(default_factory=list)
    texture_points: list[np.ndarray] = field(default_factory=list)
    texture_colours: list[np.ndarray] = field(default_factory=list)
    part_symmetries: list[np.ndarray] = field(default_factory=list)
    odd_points: list[np.ndarray] = field(default_factory=list)
    surface_points: list[np.ndarray] = field(default_factory=list)
    surface_normals: list[np.ndarray] = field(default_factory=list)

    def index(self, obj_id: int) -> int:
        """Row of ``obj_id`` in the table; ArgenError when the file has no such object."""
        hit = np.flatnonzero(self.ids == int(obj_id))
        if len(hit) == 0:
            raise ArgenError(f"object id {obj_id} is not in the label file (ids: {', '.join(map(str, self.ids))})")
        return int(hit[0])

    def __len__(self) -> int:
        return len(self.ids)


@dataclass
class InstanceTable:
    """A frame's ground-truth instances (I rows).

    obj_id, gt_index: (I,) int32; R: (I,3,3) float32 model->camera; t: (I,3) float32 metres;
    control_points: (I,9,3) float32 camera frame, metres; visib_fract: (I,) float32; num_points: (I,) int32.
    """

    obj_id: np.ndarray
    gt_index: np.ndarray
    R: np.ndarray
    t: np.ndarray
    control_points: np.ndarray
    visib_fract: np.ndarray
    num_points: np.ndarray

    def __len__(self) -> int:
        return len(self.obj_id)


@dataclass
class FrameLabels:
    """One labelled frame (N points, I instances).

    cam_K: (3,3) float32 pixels; image_size: (2,) int32 (h, w);
    features: (N,9) float32 [X,Y,Z (m), R,G,B in [0,1], Nx,Ny,Nz unit]; pixel: (N,2) int32 (row, col);
    semantic: (N,) int32 obj_id, 0 = background; instance: (N,) int32 row in ``instances``, -1 = background;
    control_points: (N,9,3) float32 camera frame, metres, zeros for background.
    """

    scene_id: int
    im_id: int
    cam_K: np.ndarray
    image_size: np.ndarray
    features: np.ndarray
    pixel: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    control_points: np.ndarray
    instances: InstanceTable = field(repr=False)

    def __len__(self) -> int:
        return len(self.features)


def point_control_points(instance_cps: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """Per-point control points gathered from the instance rows.

    instance_cps: (I,9,3) float32 metres; instance: (N,) int row, -1 = background.
    Returns (N,9,3) float32, zeros for background.
    """
    instance = np.asarray(instance)
    out = np.zeros((len(instance), 9, 3), np.float32)
    fg = instance >= 0
    if len(instance_cps):
        out[fg] = np.asarray(instance_cps, np.float32)[instance[fg]]
    return out


# ---------------------------------------------------------------------------------------- reader


def _optional_tables(o, n: int, path) -> dict:
    """The object group's optional tables (see :class:`ObjectTable`: shape symmetries and texture samples, part
    symmetries and odd points, surface samples and normals) as its keyword arguments; none of a group the file was
    written without."""
    out = {}
    for key, name, offsets, dtype, shape in (
            ("shape_symmetries", "shape_sym", "shape_sym_offsets", np.float32, (4, 4)),
            ("texture_points", "texture_points", "texture_offsets", np.float32, (3,)),
            ("texture_colours", "texture_colours", "texture_offsets", np.uint8, (3,)),
            ("part_symmetries", "part_sym", "part_sym_offsets", np.float32, (4, 4)),
            ("odd_points", "odd_points", "odd_offsets", np.float32, (3,)),
            ("surface_points", "surface_points", "surface_offsets", np.float32, (3,)),
            ("surface_normals", "surface_normals", "surface_offsets", np.float32, (3,))):
        if name not in o:
            continue
        off = o[offsets][()].astype(np.int64)
        data = o[name][()].astype(dtype).reshape(-1, *shape)
        if len(off) != n + 1 or off[-1] != len(data) or np.any(np.diff(off) < 0):
            raise ArgenError(f"label file {path} is inconsistent: objects/{name} does not match its offsets")
        out[key] = [data[off[m]:off[m + 1]] for m in range(n)]
    return out


def _text(v) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


class LabelFile:
    """Read-only view of a schema-v1 label file; a context manager.

    Raises ArgenError (one line) for a missing, truncated, foreign or wrong-schema file.
    path: Path; num_frames: int; attrs: dict of the root attributes; objects: ObjectTable.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        if not self.path.is_file():
            raise ArgenError(f"label file not found: {self.path}")
        try:
            self._f = h5py.File(self.path, "r")
        except OSError as exc:
            raise ArgenError(f"cannot read label file {self.path}: truncated or not an HDF5 file") from exc
        try:
            self._open()
        except ArgenError:
            self.close()
            raise
        except (KeyError, OSError, ValueError, TypeError) as exc:
            self.close()
            raise ArgenError(f"label file {self.path} is damaged or not written by argen label "
                             f"({exc.__class__.__name__}: {exc})") from exc

    def _open(self) -> None:
        f = self._f
        if "schema_version" not in f.attrs:
            raise ArgenError(f"{self.path} is not an argen label file (no schema_version attribute)")
        version = int(f.attrs["schema_version"])
        if version != SCHEMA_VERSION:
            raise ArgenError(f"{self.path} has label schema version {version}; this argen reads version "
                             f"{SCHEMA_VERSION}: relabel the dataset with this argen")
        missing = [a for a in ROOT_ATTRS if a not in f.attrs]
        missing += [f"{g}/{k}" for g, keys in (("objects", OBJECT_FIELDS), ("frames", list(FRAME_FIELDS) +
                    ["point_offsets", "instance_offsets"]), ("points", POINT_FIELDS),
                    ("instances", INSTANCE_FIELDS)) for k in keys if f"{g}/{k}" not in f]
        if missing:
            raise ArgenError(f"label file {self.path} lacks {', '.join(missing[:4])}"
                             + (f" and {len(missing) - 4} more" if len(missing) > 4 else ""))
        self.attrs = {k: (_text(v) if isinstance(v, (bytes, str)) else v.item() if hasattr(v, "item") else v)
                      for k, v in f.attrs.items()}
        self.num_frames = int(self.attrs["num_frames"])
        self._pt_off = f["frames/point_offsets"][()].astype(np.int64)
        self._in_off = f["frames/instance_offsets"][()].astype(np.int64)
        n_pts, n_inst = len(f["points/semantic"]), len(f["instances/obj_id"])
        if (len(self._pt_off) != self.num_frames + 1 or len(self._in_off) != self.num_frames + 1
                or self._pt_off[-1] != n_pts or self._in_off[-1] != n_inst
                or np.any(np.diff(self._pt_off) < 0) or np.any(np.diff(self._in_off) < 0)):
            raise ArgenError(f"label file {self.path} is inconsistent: its frame offsets do not match "
                             f"{self.num_frames} frames, {n_pts} points, {n_inst} instances")
        self._frames = {k: f[f"frames/{k}"][()] for k in FRAME_FIELDS}
        o = f["objects"]
        sym_off = o["sym_offsets"][()].astype(np.int64)
        sym = o["sym_transforms"][()].astype(np.float32)
        ids = o["ids"][()].astype(np.int32)
        if len(sym_off) != len(ids) + 1:
            raise ArgenError(f"label file {self.path} is inconsistent: objects/sym_offsets has {len(sym_off)} "
                             f"rows for {len(ids)} objects")
        self.objects = ObjectTable(
            ids=ids,
            names=[_text(n) for n in o["names"][()]],
            diameters=o["diameters"][()].astype(np.float32),
            symmetric=o["symmetric"][()].astype(bool),
            corners=o["corners"][()].astype(np.float32),
            control_points=o["control_points"][()].astype(np.float32),
            model_points=o["model_points"][()].astype(np.float32),
            sym_transforms=[sym[sym_off[m]:sym_off[m + 1]] for m in range(len(ids))],
            **_optional_tables(o, len(ids), self.path),
        )

    def __len__(self) -> int:
        return self.num_frames

    def _check_index(self, i: int) -> None:
        if not (0 <= int(i) < self.num_frames):
            raise IndexError(f"frame {i} out of range (file has {self.num_frames} frames)")

    def frame(self, i: int) -> FrameLabels:
        """Frame ``i`` (0-based) with its points, instances and per-point control points."""
        self._check_index(i)
        if self._f is None:
            raise ValueError(f"label file {self.path} is closed")
        f = self._f
        a, b = int(self._pt_off[i]), int(self._pt_off[i + 1])
        c, d = int(self._in_off[i]), int(self._in_off[i + 1])
        try:
            pts = {k: f[f"points/{k}"][a:b] for k in POINT_FIELDS}
            inst = InstanceTable(**{k: f[f"instances/{k}"][c:d] for k in INSTANCE_FIELDS})
        except OSError as exc:  # a corrupt chunk: h5py's message spans several lines
            raise ArgenError(f"label file {self.path} is damaged: cannot read frame {i} "
                             f"({str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__})") from exc
        return FrameLabels(
            scene_id=int(self._frames["scene_id"][i]), im_id=int(self._frames["im_id"][i]),
            cam_K=np.asarray(self._frames["cam_K"][i], np.float32),
            image_size=np.asarray(self._frames["image_size"][i], np.int32),
            features=pts["features"], pixel=pts["pixel"], semantic=pts["semantic"], instance=pts["instance"],
            control_points=point_control_points(inst.control_points, pts["instance"]),
            instances=inst,
        )

    def frames(self):
        """Iterate over all frames in order."""
        for i in range(self.num_frames):
            yield self.frame(i)

    def close(self) -> None:
        if getattr(self, "_f", None) is not None:
            self._f.close()
            self._f = None

    def __enter__(self) -> "LabelFile":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __reduce__(self):
        raise TypeError("a LabelFile holds an open HDF5 handle and cannot be pickled: open it in each worker")


# ---------------------------------------------------------------------------------------- writer


class LabelWriter:
    """Stream frames into a new label file; it appears at ``path`` (atomic rename) on :meth:`close`.

    attrs: the root attributes except schema_version and num_frames (filled in here).
    compression: "lzf" (fast, built into h5py), "gzip" (level 4, with shuffle: smaller, readable by any
    HDF5 tool, ~3x slower to write) or None (for temporary parts).
    Memory stays bounded: points and instances go to disk frame by frame; only the per-frame
    scalars (a few dozen bytes a frame) are kept until the end.
    """

    def __init__(self, path: str | os.PathLike, attrs: dict, objects: ObjectTable, compression: str | None = "lzf"):
        self.path = Path(path)
        self._ctx = atomic_path(self.path)
        self._tmp = self._ctx.__enter__()
        if compression not in COMPRESSION:
            raise ValueError(f"compression must be one of {list(COMPRESSION)}, got {compression!r}")
        self._comp = COMPRESSION[compression]
        try:
            self._f = h5py.File(self._tmp, "w", track_order=False)
            self._f.attrs["schema_version"] = SCHEMA_VERSION
            for k, v in attrs.items():
                self._f.attrs[k] = v
            self._write_objects(objects)
            for g, fields, chunk in (("points", POINT_FIELDS, POINT_CHUNK), ("instances", INSTANCE_FIELDS, INSTANCE_CHUNK)):
                grp = self._f.create_group(g)
                for k, (shape, dtype) in fields.items():
                    grp.create_dataset(k, shape=(0, *shape), maxshape=(None, *shape), dtype=dtype,
                                       chunks=(chunk, *shape), track_times=False, **self._comp)
        except BaseException:
            self.abort()
            raise
        self._frames: dict[str, list] = {k: [] for k in FRAME_FIELDS}
        self._pt_off, self._in_off = [0], [0]
        self.num_frames = 0

    def _dataset(self, name: str, data: np.ndarray) -> None:
        data = np.asarray(data)
        comp = self._comp if data.size > 256 and data.dtype.kind != "O" else {}
        self._f.create_dataset(name, data=data, track_times=False, **comp)

    def _write_objects(self, o: ObjectTable) -> None:
        self._f.create_group("objects")
        self._dataset("objects/ids", np.asarray(o.ids, np.int32))
        self._f.create_dataset("objects/names", data=np.array(list(o.names), dtype=h5py.string_dtype()),
                               track_times=False)
        self._dataset("objects/diameters", np.asarray(o.diameters, np.float32))
        self._dataset("objects/symmetric", np.asarray(o.symmetric, bool))
        self._dataset("objects/corners", np.asarray(o.corners, np.float32).reshape(-1, 8, 3))
        self._dataset("objects/control_points", np.asarray(o.control_points, np.float32).reshape(-1, 9, 3))
        self._dataset("objects/model_points", np.asarray(o.model_points, np.float32))
        self._ragged("objects/sym", [np.asarray(s, np.float32).reshape(-1, 4, 4) for s in o.sym_transforms],
                     "transforms", empty=np.zeros((0, 4, 4), np.float32))
        if o.shape_symmetries:
            self._ragged("objects/shape_sym", [np.asarray(s, np.float32).reshape(-1, 4, 4) for s in o.shape_symmetries])
            self._ragged("objects/texture", [np.asarray(p, np.float32).reshape(-1, 3) for p in o.texture_points],
                         "points")
            self._ragged("objects/texture", [np.asarray(c, np.uint8).reshape(-1, 3) for c in o.texture_colours],
                         "colours", offsets=False)
        if o.part_symmetries:
            self._ragged("objects/part_sym", [np.asarray(s, np.float32).reshape(-1, 4, 4) for s in o.part_symmetries])
            self._ragged("objects/odd", [np.asarray(p, np.float32).reshape(-1, 3) for p in o.odd_points], "points")
        if o.surface_points:
            self._ragged("objects/surface", [np.asarray(p, np.float32).reshape(-1, 3) for p in o.surface_points],
                         "points")
            self._ragged("objects/surface", [np.asarray(n, np.float32).reshape(-1, 3) for n in o.surface_normals],
                         "normals", offsets=False)

    def _ragged(self, name: str, rows: list[np.ndarray], part: str = "", offsets: bool = True,
                empty: np.ndarray | None = None) -> None:
        """Per-object arrays (R_m, ...) of varying length R_m as ``NAME_offsets`` (M+1,) int64 and ``NAME[_PART]``
        (concatenated); ``empty``: what is written for a table of no objects (its dtype and row shape)."""
        if offsets:
            self._dataset(f"{name}_offsets", np.r_[0, np.cumsum([len(r) for r in rows])].astype(np.int64))
        self._dataset(f"{name}_{part}" if part else name, np.concatenate(rows) if rows else empty)

    def _append(self, group: str, fields: dict, values: dict, start: int, n: int) -> None:
        for k, (shape, dtype) in fields.items():
            ds = self._f[f"{group}/{k}"]
            ds.resize((start + n, *shape))
            if n:
                ds[start:start + n] = np.asarray(values[k], dtype).reshape(n, *shape)

    def _write_error(self, exc: OSError) -> ArgenError:
        self.abort()
        msg = str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__
        return ArgenError(f"cannot write {self.path} ({msg}); nothing was left at that path")

    def append(self, frame: FrameLabels) -> None:
        """Add one frame (its per-point control points are not stored: they follow from the instances)."""
        try:
            self._append_frame(frame)
        except OSError as exc:  # disk full, quota: h5py raises OSError with a multi-line message
            raise self._write_error(exc) from exc

    def _append_frame(self, frame: FrameLabels) -> None:
        n, m = len(frame.features), len(frame.instances)
        self._append("points", POINT_FIELDS, {k: getattr(frame, k) for k in POINT_FIELDS}, self._pt_off[-1], n)
        self._append("instances", INSTANCE_FIELDS, {k: getattr(frame.instances, k) for k in INSTANCE_FIELDS},
                     self._in_off[-1], m)
        self._pt_off.append(self._pt_off[-1] + n)
        self._in_off.append(self._in_off[-1] + m)
        for k in FRAME_FIELDS:
            self._frames[k].append(getattr(frame, k))
        self.num_frames += 1

    @property
    def num_points(self) -> int:
        return int(self._pt_off[-1])

    @property
    def num_instances(self) -> int:
        return int(self._in_off[-1])

    def extend(self, lf: LabelFile) -> None:
        """Append every frame of another label file (same objects) in bulk: one read and write per dataset."""
        try:
            self._extend(lf)
        except OSError as exc:
            raise self._write_error(exc) from exc

    def _extend(self, lf: LabelFile) -> None:
        f = lf._f
        n, m = int(lf._pt_off[-1]), int(lf._in_off[-1])
        self._append("points", POINT_FIELDS, {k: f[f"points/{k}"][()] for k in POINT_FIELDS}, self._pt_off[-1], n)
        self._append("instances", INSTANCE_FIELDS, {k: f[f"instances/{k}"][()] for k in INSTANCE_FIELDS},
                     self._in_off[-1], m)
        self._pt_off.extend((self._pt_off[-1] + lf._pt_off[1:]).tolist())
        self._in_off.extend((self._in_off[-1] + lf._in_off[1:]).tolist())
        for k in FRAME_FIELDS:
            self._frames[k].extend(list(lf._frames[k]))
        self.num_frames += lf.num_frames

    def close(self) -> Path:
        """Write the frame tables, close and rename onto ``path``; returns ``path``."""
        try:
            fr = self._f.create_group("frames")
            for k, (shape, dtype) in FRAME_FIELDS.items():
                data = np.asarray(self._frames[k], dtype).reshape(self.num_frames, *shape)
                fr.create_dataset(k, data=data, track_times=False)
            fr.create_dataset("point_offsets", data=np.asarray(self._pt_off, np.int64), track_times=False)
            fr.create_dataset("instance_offsets", data=np.asarray(self._in_off, np.int64), track_times=False)
            self._f.attrs["num_frames"] = self.num_frames
            self._f.close()
            self._f = None
        except OSError as exc:
            raise self._write_error(exc) from exc
        except BaseException:
            self.abort()
            raise
        self._ctx.__exit__(None, None, None)
        return self.path

    def abort(self) -> None:
        """Drop the temporary file; nothing appears at ``path``."""
        f = getattr(self, "_f", None)
        if f is not None:
            try:
                f.close()
            except Exception:  # already broken: the file is discarded anyway
                pass
            self._f = None
        Path(self._tmp).unlink(missing_ok=True)

    def __enter__(self) -> "LabelWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_label_file(path: str | os.PathLike, attrs: dict, objects: ObjectTable, frames, compression="lzf") -> Path:
    """Write ``frames`` (an iterable of FrameLabels) as a label file at ``path`` atomically."""
    with LabelWriter(path, attrs, objects, compression=compression) as w:
        for fr in frames:
            w.append(fr)
    return Path(path)
