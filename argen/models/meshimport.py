"""Bring your own object: any mesh file in, a BOP models folder out (``argen models import``).

Reads what trimesh reads (OBJ with MTL textures, STL, PLY, GLB/GLTF, OFF), decides or applies the units,
repairs what can be repaired (duplicate vertices, degenerate and repeated faces, inconsistent winding,
inward normals, holes whose boundary is a simple loop), refuses what cannot (no faces, no area, a flat mesh,
an open mesh it cannot close), bakes texture colours into vertex colours, finds the symmetries
(:mod:`argen.models.symmetry`) and writes, in millimetres:

    OUT/obj_NNNNNN.ply, OUT/models_info.json (with symmetries), OUT/names.json ({id: file stem}),
    OUT/models_eval/ (BOP's evaluation models, see :func:`argen.models.objects.eval_mesh`)

Ids: a file named ``obj_NNNNNN`` keeps NNNNNN; a stem already in OUT/names.json keeps its id; new stems get
the next free ids in name order. Importing the same files again rewrites the same bytes.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from argen import bop
from argen.errors import ArgenError
from argen.fileio import read_json
from argen.models.objects import (
    ObjectModel,
    info_from_mesh,
    load_models,
    load_objects,
    read_names,
    select_ids,
    write_models,
    write_models_eval,
)
from argen.models.symmetry import DEFAULT_TOL, Symmetries, find_part_symmetry, find_symmetries, turn
from argen.models.texture import PRINT_TOL, print_moves

#: File types read (what trimesh loads as triangle meshes).
MESH_SUFFIXES = (".obj", ".stl", ".ply", ".glb", ".gltf", ".off")
#: Vertex colour of a model without colours or textures (RGBA).
NEUTRAL_RGBA = (170, 170, 170, 255)
UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001}
#: ``--units auto``: a file whose largest extent is below this many units is read as metres, else as mm.
AUTO_METRES_BELOW = 5.0
_AXES = {"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1)}


@dataclass
class ImportOptions:
    """units: auto|mm|cm|m; origin: keep|centre (the box centre); up: the file's axis that points up when the
    object rests (x, y, z, -x, -y, -z; it becomes +z), or None to keep the axes; symmetry: auto|none|a JSON
    file ({stem, name or id: {"symmetries_discrete": [...], "symmetries_continuous": [...]}} in BOP's mm form;
    objects it does not list are searched); symmetry_tol: fraction of the diameter (:mod:`argen.models.symmetry`)."""

    units: str = "auto"
    origin: str = "keep"
    up: str | None = None
    symmetry: str = "auto"
    symmetry_tol: float = DEFAULT_TOL

    def check(self) -> None:
        if self.units not in ("auto", *UNIT_SCALE):
            raise ArgenError(f"--units must be auto, mm, cm or m, got '{self.units}'")
        if self.origin not in ("keep", "centre", "center"):
            raise ArgenError(f"--origin must be keep or centre, got '{self.origin}'")
        if self.up is not None and self.up.lstrip("+-").lower() not in _AXES:
            raise ArgenError(f"--up must be x, y, z, -x, -y or -z, got '{self.up}'")
        if not 0 < self.symmetry_tol < 1:
            raise ArgenError(f"--symmetry-tol is a fraction of the diameter in (0, 1), got {self.symmetry_tol}")
        if self.symmetry not in ("auto", "none") and not Path(self.symmetry).is_file():
            raise ArgenError(f"--symmetry must be auto, none or a JSON file; {self.symmetry} is not a file")


@dataclass
class ImportedObject:
    """One imported mesh: the model (metres) and what was decided on the way, for the user to check."""

    model: ObjectModel
    path: Path
    units: str
    units_note: str
    repairs: list[str] = field(default_factory=list)
    symmetry: Symmetries | None = None
    symmetry_note: str = ""
    coloured: bool = True

    def lines(self) -> list[str]:
        ext = self.model.info.bbox_size * 1000
        head = (f"obj_{self.model.obj_id:06d} {self.model.name} ({self.path.name}): "
                f"{ext[0]:.1f} x {ext[1]:.1f} x {ext[2]:.1f} mm, diameter {self.model.diameter * 1000:.1f} mm")
        out = [head, f"  units: {self.units_note}"]
        if self.repairs:
            out.append("  repaired: " + "; ".join(self.repairs))
        out.append("  colour: " + ("from the file" if self.coloured else "none in the file: neutral grey"))
        out.append(f"  symmetry: {self.symmetry_note}")
        return out


# ----------------------------------------------------------------------------------- finding files


def is_bop_models(folder: Path) -> bool:
    """True for a folder with BOP models (obj_NNNNNN.ply) and their models_info.json."""
    return folder.is_dir() and (folder / "models_info.json").is_file() and any(folder.glob("obj_*.ply"))


def mesh_files(paths: list[Path]) -> list[Path]:
    """The mesh files named, folders expanded (their mesh files, not recursive), sorted within a folder."""
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in MESH_SUFFIXES)
            if not found:
                raise ArgenError(f"{p} holds no mesh files ({', '.join(MESH_SUFFIXES)})")
            out.extend(found)
        elif p.is_file():
            if p.suffix.lower() not in MESH_SUFFIXES:
                raise ArgenError(f"{p}: not a mesh file type argen reads ({', '.join(MESH_SUFFIXES)})")
            out.append(p)
        else:
            raise ArgenError(f"mesh file or folder not found: {p}")
    stems: dict[str, Path] = {}
    for f in out:
        if f.stem in stems and stems[f.stem] != f:
            raise ArgenError(f"two meshes with the name '{f.stem}': {stems[f.stem]} and {f}; rename one")
        stems[f.stem] = f
    return list(dict.fromkeys(out))


# ------------------------------------------------------------------------------------ one mesh


def _vertex_colours(mesh: trimesh.Trimesh) -> np.ndarray | None:
    """(V,4) uint8 colours: baked from a texture, from vertex or face colours; None when there are none."""
    vis = mesh.visual
    kind = getattr(vis, "kind", None)
    try:
        if kind == "texture":
            return np.asarray(vis.to_color().vertex_colors, np.uint8)
        if kind in ("vertex", "face"):
            return np.asarray(vis.vertex_colors, np.uint8)
    except Exception:  # a texture trimesh cannot sample (missing image, no UVs): fall back to neutral
        return None
    return None


def read_source_mesh(path: Path) -> tuple[trimesh.Trimesh, bool]:
    """All triangle geometry of a mesh file as one mesh (file units), and whether it had colours. Scene files
    (GLB, multi-material OBJ) are flattened with their node transforms."""
    try:
        scene = trimesh.load(str(path), force="scene")
        parts = [g for g in scene.dump() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    except Exception as exc:  # trimesh raises many kinds on corrupt input
        raise ArgenError(f"cannot read mesh {path}: corrupt or not a mesh ({exc.__class__.__name__}: {exc})") from exc
    if not parts:
        raise ArgenError(f"{path} holds no triangle mesh (no faces)")
    verts, faces, cols, coloured, offset = [], [], [], False, 0
    for g in parts:
        c = _vertex_colours(g)
        coloured |= c is not None
        verts.append(np.asarray(g.vertices, float))
        faces.append(np.asarray(g.faces, np.int64) + offset)
        cols.append(c if c is not None else np.tile(np.array(NEUTRAL_RGBA, np.uint8), (len(g.vertices), 1)))
        offset += len(g.vertices)
    v = np.vstack(verts)
    if not np.all(np.isfinite(v)):
        raise ArgenError(f"{path} has non-finite vertices")
    mesh = trimesh.Trimesh(v, np.vstack(faces), vertex_colors=np.vstack(cols), process=False)
    return mesh, coloured


def decide_units(extent: float, units: str) -> tuple[float, str, str]:
    """Scale to metres for a file whose largest extent is ``extent`` file units: (scale, units, note)."""
    if units != "auto":
        return UNIT_SCALE[units], units, f"{units} (given)"
    u = "m" if extent < AUTO_METRES_BELOW else "mm"
    size = extent * UNIT_SCALE[u]
    note = (f"auto: read as {'metres' if u == 'm' else 'millimetres'} (largest extent {extent:.4g} file units = "
            f"{size * 1000:.1f} mm; below {AUTO_METRES_BELOW:g} means metres); pass --units if that is wrong")
    if u == "mm" and size < 0.02:
        note += f"; small for millimetres: if the file is in cm use --units cm ({extent * 10:.0f} mm)"
    return UNIT_SCALE[u], u, note


def _up_rotation(up: str | None) -> np.ndarray | None:
    if up is None:
        return None
    sign = -1.0 if up.startswith("-") else 1.0
    a = sign * np.array(_AXES[up.lstrip("+-").lower()], float)
    if np.allclose(a, (0, 0, 1)):
        return None
    if np.allclose(a, (0, 0, -1)):
        return np.diag([1.0, -1.0, -1.0, 1.0])  # half turn about x
    return trimesh.geometry.align_vectors(a, np.array([0.0, 0.0, 1.0]))


def _boundary_loops(mesh: trimesh.Trimesh) -> list[list[int]] | None:
    """Closed loops of boundary edges as vertex lists, each in the direction its faces use them; None when the
    boundary is not a set of simple loops (a vertex with two outgoing boundary edges)."""
    edges = np.asarray(mesh.edges)  # directed, from the faces
    once = trimesh.grouping.group_rows(np.asarray(mesh.edges_sorted), require_count=1)
    nxt: dict[int, int] = {}
    for a, b in edges[once]:
        if int(a) in nxt:
            return None
        nxt[int(a)] = int(b)
    loops, seen = [], set()
    for start in nxt:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            if v not in nxt:
                return None
            v = nxt[v]
        if v != start:
            return None
        loops.append(loop)
    return loops


def _close_holes(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, int]:
    """Cap every simple boundary loop with a fan around the loop's centroid (faces oriented like the rest)."""
    loops = _boundary_loops(mesh)
    if not loops:
        return mesh, 0
    v = list(np.asarray(mesh.vertices))
    cols = list(np.asarray(mesh.visual.vertex_colors))
    faces = list(np.asarray(mesh.faces))
    for loop in loops:
        k = len(v)
        v.append(np.asarray(mesh.vertices)[loop].mean(axis=0))
        cols.append(np.asarray(mesh.visual.vertex_colors)[loop].mean(axis=0).astype(np.uint8))
        for a, b in zip(loop, loop[1:] + loop[:1]):
            faces.append([b, a, k])  # the edge a->b is used by a face; the cap uses b->a
    return trimesh.Trimesh(np.array(v), np.array(faces), vertex_colors=np.array(cols), process=False), len(loops)


def edge_counts(mesh: trimesh.Trimesh) -> np.ndarray:
    """How many faces use each undirected edge (one count per unique edge)."""
    _, counts = np.unique(np.asarray(mesh.edges_sorted), axis=0, return_counts=True)
    return counts


def repair(mesh: trimesh.Trimesh, path: Path) -> tuple[trimesh.Trimesh, list[str]]:
    """Repair what trimesh can; raise ArgenError for a mesh that cannot be a solid object.

    Closed means no edge is used by one face only: a single closed surface (2 faces per edge), or closed
    parts that touch or overlap (as assemblies exported as one mesh are: 3 or more faces at some edges).
    Edges used once are holes: their loops are capped when they form simple loops, else the mesh is refused.
    """
    notes = []
    n_v, n_f = len(mesh.vertices), len(mesh.faces)
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.vertices) < n_v:
        notes.append(f"merged or dropped {n_v - len(mesh.vertices)} duplicate or unused vertices")
    if len(mesh.faces) < n_f:
        notes.append(f"dropped {n_f - len(mesh.faces)} degenerate or repeated faces")
    if len(mesh.faces) < 4 or mesh.area <= 0:
        raise ArgenError(f"{path}: degenerate mesh ({len(mesh.faces)} faces with area left after cleaning)")
    ext = mesh.extents
    if ext.min() <= 1e-6 * ext.max():
        raise ArgenError(f"{path}: zero extent along {'xyz'[int(np.argmin(ext))]}: a flat mesh, not a solid object")
    counts = edge_counts(mesh)
    if np.any(counts == 1):
        trimesh.repair.fill_holes(mesh)
        if np.any(edge_counts(mesh) == 1):
            mesh, n = _close_holes(mesh)
            if n:
                mesh.merge_vertices()
        counts = edge_counts(mesh)
        if np.any(counts == 1):
            raise ArgenError(f"{path}: open mesh that argen cannot close (its boundary is not a set of simple "
                             "loops); close it in a mesh editor")
        notes.append("closed holes in the surface")
    if np.any(counts > 2):
        notes.append("kept edges shared by more than two faces (parts that touch)")
    if mesh.is_watertight:  # one 2-manifold surface: winding and orientation can be fixed
        if not mesh.is_winding_consistent:
            trimesh.repair.fix_winding(mesh)
            notes.append("made the face winding consistent")
        if mesh.volume < 0:
            mesh.invert()
            notes.append("turned the normals outwards")
    return mesh, notes


def _symmetries_file(path: str) -> dict[str, tuple[list, list]]:
    raw = read_json(Path(path), "symmetry file")
    if not isinstance(raw, dict):
        raise ArgenError(f"{path}: expected an object keyed by file stem, name or id")
    return {str(k).lower(): bop.parse_symmetries(v, f"{path} entry '{k}'") for k, v in raw.items()}


def _keep_printed(mesh: trimesh.Trimesh, info) -> str:
    """Drop from ``info`` the symmetries the mesh's print breaks (:func:`argen.models.texture.print_moves`): BOP
    lists an object's symmetries with its texture in mind, and a printed box turned half way is another pose. A
    continuous symmetry is kept when quarter, half and three-quarter turns about its axis keep the print. Returns
    a note for the import report ("" when nothing was dropped); the dropped turns are left to the detector's colour
    check (argen label stores them as the object's shape symmetries)."""
    disc = list(info.symmetries_discrete)
    cont = list(info.symmetries_continuous)
    turns = [turn(np.asarray(c["axis"], float), a, np.asarray(c["offset"], float))
             for c in cont for a in (np.pi / 2, np.pi, 1.5 * np.pi)]
    moved = print_moves(mesh, info.diameter, disc + turns)
    keep_d = [S for S, m in zip(disc, moved[:len(disc)]) if m < PRINT_TOL]
    keep_c = [c for k, c in enumerate(cont) if np.all(moved[len(disc) + 3 * k:len(disc) + 3 * k + 3] < PRINT_TOL)]
    dropped = len(disc) - len(keep_d) + len(cont) - len(keep_c)
    if not dropped:
        return ""
    info.symmetries_discrete, info.symmetries_continuous = keep_d, keep_c
    return (f"; {dropped} of them broken by its print, not listed (kept: {len(keep_d)} discrete, "
            f"{len(keep_c)} continuous)")


def import_mesh(path: Path, obj_id: int, opts: ImportOptions,
                given: dict[str, tuple[list, list]] | None = None) -> ImportedObject:
    """Read, convert to metres, orient, repair, colour and analyse one mesh file as object ``obj_id``."""
    mesh, coloured = read_source_mesh(path)
    scale, units, note = decide_units(float(mesh.extents.max()), opts.units)
    mesh.apply_scale(scale)
    R = _up_rotation(opts.up)
    if R is not None:
        mesh.apply_transform(R)
    mesh, repairs = repair(mesh, path)
    if opts.origin in ("centre", "center"):
        mesh.apply_translation(-(mesh.bounds[0] + mesh.bounds[1]) / 2)
    mesh = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces),
                           vertex_colors=np.asarray(mesh.visual.vertex_colors), process=False)
    name = path.stem
    info = info_from_mesh(mesh)
    sym, sym_note = None, "none (--symmetry none)"
    key_hits = [k for k in (name.lower(), str(obj_id)) if given and k in given]
    if key_hits:
        info.symmetries_discrete, info.symmetries_continuous = given[key_hits[0]]
        sym_note = (f"from {opts.symmetry}: {len(info.symmetries_discrete)} discrete, "
                    f"{len(info.symmetries_continuous)} continuous")
    elif opts.symmetry != "none":
        sym = find_symmetries(mesh, info.diameter, tol=opts.symmetry_tol)
        info.symmetries_discrete, info.symmetries_continuous = list(sym.discrete), list(sym.continuous)
        sym_note = sym.describe()
        if coloured and (sym.discrete or sym.continuous):
            sym_note += _keep_printed(mesh, info)
        if not info.symmetries_continuous:  # what `argen label` will store for it (argen.label.object_table)
            part = find_part_symmetry(mesh, info.diameter)
            sym_note += "; part symmetry: " + ("none" if part is None else part.describe())
    model = ObjectModel(obj_id, name, mesh, info, source=str(path))
    return ImportedObject(model, path, units, note, repairs, sym, sym_note, coloured)


# --------------------------------------------------------------------------------- many meshes


def _stem_id(stem: str) -> int | None:
    m = re.fullmatch(r"obj_(\d+)", stem)
    return int(m.group(1)) if m else None


def assign_ids(files: list[Path], known: dict[str, int]) -> dict[Path, int]:
    """Ids for the files: obj_NNNNNN stems keep NNNNNN, known stems keep theirs, the rest get the next free
    ids in name order."""
    out: dict[Path, int] = {}
    taken = set(known.values())
    for f in files:
        i = _stem_id(f.stem)
        if i is None:
            i = known.get(f.stem)
        if i is not None:
            if i in out.values():
                raise ArgenError(f"{f}: object id {i} is given twice")
            out[f] = i
            taken.add(i)
    nxt = max(taken, default=0) + 1
    for f in sorted((f for f in files if f not in out), key=lambda f: f.stem):
        while nxt in taken:
            nxt += 1
        out[f] = nxt
        taken.add(nxt)
    return out


def import_meshes(paths: list[Path], opts: ImportOptions | None = None,
                  known: dict[str, int] | None = None) -> list[ImportedObject]:
    """Import mesh files and folders (nothing is written); sorted by id."""
    opts = opts or ImportOptions()
    opts.check()
    files = mesh_files(paths)
    given = _symmetries_file(opts.symmetry) if opts.symmetry not in ("auto", "none") else None
    ids = assign_ids(files, known or {})
    return sorted((import_mesh(f, ids[f], opts, given) for f in files), key=lambda o: o.model.obj_id)


def _known_names(out: Path) -> dict[str, int]:
    raw = read_names(out) or {}
    try:
        return {str(v): int(k) for k, v in raw.items()}
    except ValueError:
        raise ArgenError(f"the names file in {out} is not an {{id: name}} map") from None


def import_to_folder(paths: list[Path], out: Path, opts: ImportOptions | None = None) -> list[ImportedObject]:
    """``argen models import``: import the meshes into the BOP models folder ``out`` (created or extended;
    objects already there stay, with their ids). Returns the imported objects."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ArgenError(f"--out {out} exists and is not a folder")
    known = _known_names(out)
    existing = {o.obj_id: o for o in load_models(out)} if is_bop_models(out) else {}
    imported = import_meshes(paths, opts, known)
    for o in imported:
        existing[o.model.obj_id] = o.model
    objects = [existing[i] for i in sorted(existing)]
    new = {o.model.obj_id for o in imported}
    write_models(out, objects, rewrite=new)
    write_models_eval(out / "models_eval", objects, rewrite=new)
    return imported


def load_any_models(models: Path | None, select: list[str] | None = None) -> tuple[list[ObjectModel], list[str]]:
    """What ``--models`` names, as objects, and lines telling the user what was done: a BOP models folder as it
    is; a folder of plain meshes, or one mesh file, imported on the fly with the default options; None: the
    built-in objects."""
    if models is None or is_bop_models(Path(models)):
        return load_objects(models, select), []
    models = Path(models)
    if models.is_file() and models.suffix.lower() in MESH_SUFFIXES:
        pass  # one mesh file
    elif not models.is_dir():
        raise ArgenError(f"models folder not found: {models}")
    elif not any(f.suffix.lower() in MESH_SUFFIXES for f in models.iterdir()):
        return load_objects(models, select), []  # load_models says what a BOP folder lacks
    imported = import_meshes([models])
    by_id = {o.model.obj_id: o for o in imported}
    chosen = select_ids(sorted(by_id), {i: o.model.name for i, o in by_id.items()}, select)
    what = "a mesh file" if models.is_file() else "not a BOP models folder (no models_info.json)"
    lines = [f"--models {models} is {what}: imported {len(imported)} mesh(es) with the default options "
             "(`argen models import` sets them); they are written to the dataset's models/"]
    for i in chosen:
        lines += by_id[i].lines()
    return [by_id[i].model for i in chosen], lines
