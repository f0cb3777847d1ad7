"""Object models: a BOP models folder or the built-in procedural stand-ins, in metres.

An :class:`ObjectModel` holds the coloured mesh (metres, model frame) and what ``models_info.json``
says about it (diameter, box, symmetries). Control points are the model-frame box's 8 corners in
``itertools.product((x0, x1), (y0, y1), (z0, z1))`` order, then the box centre.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from argen import bop
from argen.errors import ArgenError
from argen.fileio import read_json, write_json

# BOP LineMOD object ids and names (Hinterstoisser et al. 2012).
LINEMOD_NAMES = {
    1: "ape", 2: "benchvise", 3: "bowl", 4: "camera", 5: "can", 6: "cat", 7: "cup", 8: "driller",
    9: "duck", 10: "eggbox", 11: "glue", 12: "holepuncher", 13: "iron", 14: "lamp", 15: "phone",
}
NAMES_FILE = "names.json"  # {obj_id: name} written beside models_info.json by argen
LEGACY_NAMES_FILE = "argen_names.json"  # its earlier name, still read


@dataclass
class ObjectModel:
    """One object. mesh: trimesh in metres (model frame); info: its models_info entry (metres)."""

    obj_id: int
    name: str
    mesh: trimesh.Trimesh
    info: bop.ModelInfo
    source: str = ""
    _stable: tuple | None = field(default=None, repr=False)
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def diameter(self) -> float:
        return self.info.diameter

    @property
    def symmetric(self) -> bool:
        return bool(self.info.symmetries_discrete or self.info.symmetries_continuous)

    @property
    def hull_vertices(self) -> np.ndarray:
        """(V,3) vertices of the mesh's convex hull, metres (cached)."""
        if "hull" not in self._cache:
            self._cache["hull"] = np.asarray(self.mesh.convex_hull.vertices)
        return self._cache["hull"]

    @property
    def corners(self) -> np.ndarray:
        """(8,3) float64 model-frame box corners, metres."""
        return box_corners(self.info.bbox_min, self.info.bbox_size)

    @property
    def control_points(self) -> np.ndarray:
        """(9,3) float64: the 8 corners then the box centre, metres."""
        return control_points(self.info.bbox_min, self.info.bbox_size)

    def stable_poses(self, n: int = 4) -> tuple[np.ndarray, np.ndarray]:
        """The ``n`` most likely resting poses on a plane z=0: (n,4,4) transforms, (n,) probabilities.

        Each transform puts the model on the plane (lowest point at z=0) with its support polygon's
        centre of mass over the origin; computed once per object (trimesh.poses on the convex hull).
        """
        if self._stable is None or len(self._stable[0]) < n:
            hull = self.mesh.convex_hull
            transforms, probs = trimesh.poses.compute_stable_poses(hull, n_samples=1, threshold=0.0)
            self._cache.clear()
            if len(transforms) == 0:
                transforms, probs = np.eye(4)[None], np.ones(1)
            order = np.argsort(-probs)
            self._stable = (np.asarray(transforms)[order], np.asarray(probs)[order])
        T, p = self._stable
        T, p = T[:n], p[:n]
        return T, p / p.sum()


def box_corners(bbox_min: np.ndarray, bbox_size: np.ndarray) -> np.ndarray:
    """(8,3) box corners in the documented control-point order. bbox_min, bbox_size: (3,) metres."""
    lo = np.asarray(bbox_min, float)
    hi = lo + np.asarray(bbox_size, float)
    return np.array(list(itertools.product((lo[0], hi[0]), (lo[1], hi[1]), (lo[2], hi[2]))))


def control_points(bbox_min: np.ndarray, bbox_size: np.ndarray) -> np.ndarray:
    """(9,3) control points: 8 corners + centre, metres."""
    c = box_corners(bbox_min, bbox_size)
    return np.vstack([c, c.mean(axis=0, keepdims=True)])


def info_from_mesh(mesh: trimesh.Trimesh, symmetries_discrete=(), symmetries_continuous=()) -> bop.ModelInfo:
    """A models_info entry computed from a mesh in metres (diameter over the convex hull)."""
    v = mesh.convex_hull.vertices
    d = np.sqrt(((v[:, None, :] - v[None, :, :]) ** 2).sum(-1)).max()
    return bop.ModelInfo(float(d), mesh.bounds[0].copy(), (mesh.bounds[1] - mesh.bounds[0]).copy(),
                         list(symmetries_discrete), list(symmetries_continuous))


# ------------------------------------------------------------------------------- BOP models dir


def read_names(models_dir: Path) -> dict[str, str] | None:
    """The ``{"obj_id": name}`` map of a models folder (names.json, else the legacy argen_names.json), or None."""

    for name in (NAMES_FILE, LEGACY_NAMES_FILE):
        p = Path(models_dir) / name
        if p.is_file():
            raw = read_json(p, name)
            if not isinstance(raw, dict):
                raise ArgenError(f"{p} is not an {{id: name}} map")
            return raw
    return None


def surface_scene(mesh: trimesh.Trimesh):
    """An open3d RaycastingScene of the mesh's triangles, for exact point-to-surface distances and closest
    points (same units as the mesh). open3d is imported here, not at the top: every argen command imports this
    module, and open3d takes about a second to load."""
    # lazy: open3d loads in about a second (see the docstring)
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    return scene


def _names_for(models_dir: Path, ids: list[int]) -> dict[int, str]:
    raw = read_names(models_dir)
    if raw is not None:
        return {i: str(raw.get(str(i), f"obj_{i:06d}")) for i in ids}
    linemod = models_dir.resolve().parent.name.lower() in ("lm", "lmo", "linemod", "lm_full")
    return {i: (LINEMOD_NAMES.get(i, f"obj_{i:06d}") if linemod else f"obj_{i:06d}") for i in ids}


def load_models(models_dir: str | os.PathLike, select: list[str] | None = None) -> list[ObjectModel]:
    """Load a BOP models folder (``models_info.json`` + ``obj_XXXXXX.ply`` in mm) into metres.

    select: names or ids to keep (None or empty = all). Raises ArgenError on a missing or empty
    folder, a missing models_info entry, a corrupt PLY or a model that is not in millimetres.
    """
    d = Path(models_dir)
    if not d.is_dir():
        raise ArgenError(f"models folder not found: {d}")
    plys = sorted(d.glob("obj_*.ply"))
    if not plys:
        raise ArgenError(f"models folder {d} holds no obj_XXXXXX.ply models")
    infos = bop.read_models_info(d / "models_info.json")
    ids = []
    for p in plys:
        try:
            ids.append(int(p.stem.split("_")[1]))
        except (IndexError, ValueError):
            raise ArgenError(f"model file name {p.name} is not obj_XXXXXX.ply") from None
    missing = [i for i in ids if i not in infos]
    if missing:
        raise ArgenError(f"{d / 'models_info.json'} has no entry for object(s) {', '.join(map(str, missing))}")
    names = _names_for(d, ids)
    chosen = select_ids(ids, names, select)
    out = []
    for i in chosen:
        path = bop.model_path(d, i)
        mesh = bop.read_mesh(path)
        _check_units(mesh, infos[i], path)
        out.append(ObjectModel(i, names[i], mesh, infos[i], source=str(path)))
    return out


def _check_units(mesh: trimesh.Trimesh, info: bop.ModelInfo, path: Path) -> None:
    """Models are millimetres in BOP; a model whose size disagrees by ~1000x was written in metres."""
    ext = float(np.max(mesh.extents))  # metres after the mm->m conversion
    expect = float(np.max(info.bbox_size))
    if ext < 0.002 and expect >= 0.002:
        raise ArgenError(f"model {path} looks like it is in metres (largest extent {ext * 1000:.3f} mm); "
                         "BOP models must be in millimetres: scale it by 1000")
    if ext > 50.0:
        raise ArgenError(f"model {path} is {ext:.0f} m across: not millimetres?")
    if expect > 0 and not (0.5 < ext / expect < 2.0):
        raise ArgenError(f"model {path} is {ext * 1000:.1f} mm across but models_info.json says "
                         f"{expect * 1000:.1f} mm: units disagree")


def select_ids(ids: list[int], names: dict[int, str], select: list[str] | None) -> list[int]:
    """The sorted ids that ``select`` names (ids or names, case-insensitive; None or empty: all ``ids``)."""
    if not select:
        return list(ids)
    by_name = {n.lower(): i for i, n in names.items()}
    chosen = []
    for s in select:
        s = str(s).strip()
        if s.isdigit() and int(s) in ids:
            chosen.append(int(s))
        elif s.lower() in by_name:
            chosen.append(by_name[s.lower()])
        else:
            avail = ", ".join(names[i] for i in ids)
            raise ArgenError(f"unknown object '{s}' (available: {avail})")
    return sorted(set(chosen))


# --------------------------------------------------------------------------- built-in stand-ins


def _coloured(mesh: trimesh.Trimesh, rgb, rng: np.random.Generator, speckle: float = 18.0) -> trimesh.Trimesh:
    """Give a part a base colour with per-vertex speckle so it has some texture."""
    base = np.asarray(rgb, float)
    cols = np.clip(base + rng.normal(0, speckle, (len(mesh.vertices), 3)), 0, 255).astype(np.uint8)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.c_[cols, np.full(len(cols), 255, np.uint8)])
    return mesh


def _tf(mesh: trimesh.Trimesh, translate=(0, 0, 0), rotate=None) -> trimesh.Trimesh:
    if rotate is not None:
        axis, angle = rotate
        mesh.apply_transform(trimesh.transformations.rotation_matrix(angle, axis))
    mesh.apply_translation(translate)
    return mesh


def _builtin_parts(rng: np.random.Generator) -> dict[str, tuple[list[trimesh.Trimesh], dict]]:
    C = trimesh.creation
    parts: dict[str, tuple[list[trimesh.Trimesh], dict]] = {}
    # 1 bracket: an L of two boxes (no symmetry), about ape/duck size
    parts["bracket"] = ([
        _coloured(C.box((0.09, 0.05, 0.02)), (220, 120, 30), rng),
        _coloured(_tf(C.box((0.02, 0.05, 0.07)), (0.035, 0, 0.045)), (200, 90, 20), rng),
    ], {})
    # 2 mug: cylinder + handle (no symmetry because of the handle)
    parts["mug"] = ([
        _coloured(C.cylinder(0.038, 0.095, sections=40), (40, 90, 200), rng),
        _coloured(_tf(C.torus(0.025, 0.007, major_sections=24, minor_sections=10),
                      (0.045, 0, 0), rotate=((1, 0, 0), np.pi / 2)), (30, 60, 160), rng),
    ], {})
    # 3 bottle: body + neck + cap, symmetric about z (continuous symmetry)
    parts["bottle"] = ([
        _coloured(C.cylinder(0.032, 0.12, sections=40), (40, 170, 80), rng),
        _coloured(_tf(C.cone(0.032, 0.05, sections=40), (0, 0, 0.06)), (40, 150, 70), rng),
        _coloured(_tf(C.cylinder(0.011, 0.03, sections=24), (0, 0, 0.115)), (230, 230, 230), rng),
    ], {"symmetries_continuous": [{"axis": np.array([0.0, 0.0, 1.0]), "offset": np.zeros(3)}]})
    # 4 duck: ellipsoid body, head, beak (no symmetry)
    body = C.icosphere(subdivisions=3, radius=1.0)
    body.apply_scale((0.045, 0.032, 0.028))
    parts["duck"] = ([
        _coloured(body, (235, 200, 40), rng),
        _coloured(_tf(C.icosphere(subdivisions=3, radius=0.021), (0.03, 0, 0.035)), (235, 205, 50), rng),
        _coloured(_tf(C.cone(0.009, 0.025, sections=20), (0.048, 0, 0.035), rotate=((0, 1, 0), np.pi / 2)),
                  (230, 110, 20), rng),
    ], {})
    # 5 drill: body box, chuck cylinder along +x, handle box below (driller-sized, no symmetry)
    parts["drill"] = ([
        _coloured(C.box((0.15, 0.06, 0.07)), (40, 140, 140), rng),
        _coloured(_tf(C.cylinder(0.017, 0.06, sections=24), (0.1, 0, 0.01), rotate=((0, 1, 0), np.pi / 2)),
                  (60, 60, 60), rng),
        _coloured(_tf(C.box((0.045, 0.05, 0.13)), (-0.035, 0, -0.095)), (30, 110, 110), rng),
        _coloured(_tf(C.box((0.07, 0.07, 0.035)), (-0.035, 0, -0.17)), (20, 20, 20), rng),
    ], {})
    # 6 eggcrate: flat box with a 2x3 grid of domes, symmetric under a half turn about z
    domes = [
        _tf(C.icosphere(subdivisions=2, radius=0.016), (x, y, 0.012))
        for x in (-0.04, 0.0, 0.04) for y in (-0.022, 0.022)
    ]
    parts["eggcrate"] = ([
        _coloured(C.box((0.13, 0.08, 0.024)), (150, 60, 170), rng),
        *[_coloured(d, (170, 80, 190), rng) for d in domes],
    ], {"symmetries_discrete": [np.diag([-1.0, -1.0, 1.0, 1.0])]})
    return parts


BUILTIN_IDS = {"bracket": 1, "mug": 2, "bottle": 3, "duck": 4, "drill": 5, "eggcrate": 6}


def builtin_objects(select: list[str] | None = None) -> list[ObjectModel]:
    """The procedural stand-in objects (coloured, LineMOD-sized), centred on their box centre.

    Deterministic: the same meshes every call. Symmetries are exact by construction (the mesh is
    centred so that a symmetry's axis passes through the model origin).
    """
    rng = np.random.default_rng(12345)
    parts = _builtin_parts(rng)
    names = {BUILTIN_IDS[n]: n for n in parts}
    chosen = select_ids(sorted(names), names, select)
    out = []
    for obj_id in chosen:
        name = names[obj_id]
        meshes, sym = parts[name]
        mesh = trimesh.util.concatenate(meshes)
        centre = (mesh.bounds[0] + mesh.bounds[1]) / 2
        if sym:  # keep the symmetry axis through the origin: centre only along it
            axis_free = np.array([0.0, 0.0, 1.0])
            centre = centre * axis_free
        mesh.apply_translation(-centre)
        info = info_from_mesh(mesh, sym.get("symmetries_discrete", ()), sym.get("symmetries_continuous", ()))
        out.append(ObjectModel(obj_id, name, mesh, info, source="builtin"))
    return out


def load_objects(models_dir: str | os.PathLike | None, select: list[str] | None = None) -> list[ObjectModel]:
    """A BOP models folder when given, else the built-in stand-ins."""
    objs = load_models(models_dir, select) if models_dir else builtin_objects(select)
    if not objs:
        raise ArgenError("no objects selected")
    return objs


def write_models(models_dir: str | os.PathLike, objects: list[ObjectModel], evaluation: bool = False,
                 rewrite: frozenset[int] | set[int] = frozenset()) -> None:
    """Write the objects as a BOP models folder (PLY in mm, models_info.json, names.json); with
    ``evaluation``, BOP's models_eval folder instead (:func:`eval_mesh` of each object, no names file).
    A model file already there is kept unless its id is in ``rewrite``."""
    d = Path(models_dir)
    d.mkdir(parents=True, exist_ok=True)
    for o in objects:
        p = bop.model_path(d, o.obj_id)
        if not p.exists() or o.obj_id in rewrite:
            bop.write_mesh(p, eval_mesh(o.mesh, o.diameter) if evaluation else o.mesh)
    bop.write_models_info(d / "models_info.json", {o.obj_id: o.info for o in objects})
    if not evaluation:
        write_json(d / NAMES_FILE, {str(o.obj_id): o.name for o in objects})


#: Largest edge of a models_eval mesh, as a fraction of the object's diameter.
EVAL_EDGE = 0.02


def eval_mesh(mesh: trimesh.Trimesh, diameter: float, edge: float = EVAL_EDGE) -> trimesh.Trimesh:
    """The model resampled for evaluation (BOP's models_eval): the same surface with every face split until no
    edge is longer than ``edge`` x ``diameter``, so that its vertices, which BOP's MSSD / MSPD errors are computed
    on, cover the whole surface at least that densely (large flat faces included). Metres in, metres out;
    colours are not kept (evaluation does not use them)."""
    v, f = trimesh.remesh.subdivide_to_size(np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                            max_edge=edge * diameter, max_iter=20)
    return trimesh.Trimesh(v, f, process=False)


def write_models_eval(models_dir: str | os.PathLike, objects: list[ObjectModel],
                      rewrite: frozenset[int] | set[int] = frozenset()) -> None:
    """Write BOP's ``models_eval`` folder: :func:`eval_mesh` of each object (PLY in mm) and models_info.json."""
    write_models(models_dir, objects, evaluation=True, rewrite=rewrite)
