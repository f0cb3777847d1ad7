"""argen models import: any mesh in, a BOP models folder out; capture-sim takes a plain mesh folder."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import trimesh
from PIL import Image
from typer.testing import CliRunner

from argen import bop
from argen.cli.app import app
from argen.errors import ArgenError
from argen.models.meshimport import ImportOptions, edge_counts, import_meshes, import_to_folder, load_any_models
from argen.models.objects import builtin_objects, load_models

C = trimesh.creation
runner = CliRunner()


def _user_folder(d):
    """A new user's folder: widget.obj in metres (the built-in L bracket), can.stl in millimetres."""
    d.mkdir(parents=True, exist_ok=True)
    bracket = builtin_objects(["bracket"])[0].mesh.copy()
    bracket.visual = trimesh.visual.ColorVisuals(bracket)  # plain geometry, no colours
    bracket.export(d / "widget.obj")
    C.cylinder(33.0, 120.0, sections=40).export(d / "can.stl")
    return d


def _digest(d):
    return {p.relative_to(d).as_posix(): hashlib.md5(p.read_bytes()).hexdigest()
            for p in sorted(d.rglob("*")) if p.is_file()}


def test_import_units_ids_names_and_symmetries(tmp_path):
    src = _user_folder(tmp_path / "mine")
    out = tmp_path / "models"
    imported = import_to_folder([src], out)
    assert [(o.model.obj_id, o.model.name, o.units) for o in imported] == [(1, "can", "mm"), (2, "widget", "m")]
    objs = {o.name: o for o in load_models(out)}  # a valid BOP models folder, names from names.json
    assert json.loads((out / "names.json").read_text()) == {"1": "can", "2": "widget"}
    assert np.allclose(objs["can"].info.bbox_size, (0.066, 0.066, 0.12), atol=1e-6)
    assert np.allclose(objs["widget"].info.bbox_size, builtin_objects(["bracket"])[0].info.bbox_size, atol=1e-6)
    # symmetries found and written in BOP form
    assert len(objs["can"].info.symmetries_continuous) == 1 and len(objs["can"].info.symmetries_discrete) == 1
    assert not objs["widget"].symmetric
    assert (out / "models_eval" / "obj_000002.ply").is_file() and (out / "models_eval" / "models_info.json").is_file()
    # --objects works with the names
    assert [o.obj_id for o in load_models(out, ["widget"])] == [2]
    # every model is closed (the widget's two boxes touch along edges: 4 faces there) with outward normals
    for o in objs.values():
        assert np.all(edge_counts(o.mesh) >= 2) and o.mesh.volume > 0


def test_import_is_idempotent_and_keeps_ids_when_objects_are_added(tmp_path):
    src = _user_folder(tmp_path / "mine")
    out = tmp_path / "models"
    import_to_folder([src], out)
    first = _digest(out)
    import_to_folder([src], out)
    assert _digest(out) == first
    C.box((0.05, 0.04, 0.03)).export(tmp_path / "apple.off")  # sorts before can and widget, but is new
    imported = import_to_folder([tmp_path / "apple.off"], out)
    assert [(o.model.obj_id, o.model.name) for o in imported] == [(3, "apple")]
    after = _digest(out)
    assert all(after[k] == v for k, v in first.items() if "obj_00000" in k)  # old models untouched
    assert json.loads((out / "names.json").read_text()) == {"1": "can", "2": "widget", "3": "apple"}
    assert sorted(o.obj_id for o in load_models(out)) == [1, 2, 3]


def test_units_origin_and_up(tmp_path):
    C.box((10.0, 4.0, 2.0)).apply_translation((20, 0, 0)).export(tmp_path / "bar.ply")  # cm, off-centre
    (o,) = import_meshes([tmp_path / "bar.ply"], ImportOptions(units="cm", origin="centre", up="x"))
    m = o.model.mesh
    assert np.allclose(m.extents, (0.02, 0.04, 0.10), atol=1e-9)  # x (10 cm) now points up
    assert np.allclose(m.bounds.mean(axis=0), 0, atol=1e-9)
    (k,) = import_meshes([tmp_path / "bar.ply"], ImportOptions(units="cm"))
    assert np.allclose(k.model.mesh.bounds[0], (0.15, -0.02, -0.01), atol=1e-9)  # origin kept
    (a,) = import_meshes([tmp_path / "bar.ply"])  # auto: 20.0 units across -> mm, and it says so
    assert a.units == "mm" and "millimetres" in a.units_note and "small" in a.units_note


def test_texture_colours_are_baked_and_glb_reads(tmp_path):
    m = C.box((0.1, 0.06, 0.03)).subdivide().subdivide()
    uv = np.c_[(m.vertices[:, 0] + 0.05) / 0.1, (m.vertices[:, 1] + 0.03) / 0.06]
    img = np.zeros((64, 64, 3), np.uint8)
    img[:, :32] = (250, 10, 10)
    img[:, 32:] = (10, 10, 250)
    m.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(img))
    (tmp_path / "tex").mkdir()
    m.export(tmp_path / "tex" / "painted.obj")  # writes the .mtl and the texture PNG beside it
    m.export(tmp_path / "painted_glb.glb")
    for path in (tmp_path / "tex" / "painted.obj", tmp_path / "painted_glb.glb"):
        (o,) = import_meshes([path], ImportOptions(symmetry="none"))
        v = np.asarray(o.model.mesh.vertices)
        col = np.asarray(o.model.mesh.visual.vertex_colors)[:, :3].astype(int)
        left, right = v[:, 0] < -0.02, v[:, 0] > 0.02
        assert o.coloured
        assert np.all(col[left, 0] > 200) and np.all(col[left, 2] < 50), path.suffix
        assert np.all(col[right, 2] > 200) and np.all(col[right, 0] < 50), path.suffix
    # the colours survive the BOP PLY
    out = tmp_path / "models"
    import_to_folder([tmp_path / "tex" / "painted.obj"], out, ImportOptions(symmetry="none"))
    back = bop.read_mesh(out / "obj_000001.ply")
    assert np.asarray(back.visual.vertex_colors)[:, 0].max() > 200


def test_symmetries_the_print_breaks_are_not_listed(tmp_path):
    """A box's shape has three half turns; painted red on its -x half and blue on its +x half, only the turn about x
    keeps its print (BOP lists symmetries with the texture in mind). Unpainted, all three are listed."""
    m = C.box((0.1, 0.06, 0.03)).subdivide().subdivide()
    uv = np.c_[(m.vertices[:, 0] + 0.05) / 0.1, (m.vertices[:, 1] + 0.03) / 0.06]
    img = np.zeros((64, 64, 3), np.uint8)
    img[:, :32] = (250, 10, 10)
    img[:, 32:] = (10, 10, 250)
    plain = m.copy()
    m.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(img))
    m.export(tmp_path / "painted.glb")
    plain.export(tmp_path / "plain.stl")
    painted, bare = import_meshes([tmp_path / "painted.glb", tmp_path / "plain.stl"], ImportOptions(units="m"))
    assert len(bare.model.info.symmetries_discrete) == 3
    (kept,) = painted.model.info.symmetries_discrete
    np.testing.assert_allclose(np.abs(np.diag(np.asarray(kept)[:3, :3])), 1.0, atol=1e-3)
    assert np.asarray(kept)[0, 0] > 0.99  # the half turn about x: x stays
    assert "2 of them broken by its print" in painted.symmetry_note


def test_repairs_winding_inside_out_and_holes(tmp_path):
    s = C.icosphere(subdivisions=2, radius=0.04)
    f = np.asarray(s.faces).copy()
    f[::3] = f[::3, ::-1]  # a third of the faces flipped
    trimesh.Trimesh(s.vertices, f, process=False).export(tmp_path / "flipped.ply")
    trimesh.Trimesh(s.vertices, np.asarray(s.faces)[:, ::-1], process=False).export(tmp_path / "inside_out.ply")
    box = C.box((0.08, 0.05, 0.03)).subdivide()
    top = box.face_normals[:, 2] > 0.9
    trimesh.Trimesh(box.vertices, box.faces[~top], process=False).export(tmp_path / "open_box.stl")
    for name, what in [("flipped.ply", "winding"), ("inside_out.ply", "outwards"), ("open_box.stl", "closed")]:
        (o,) = import_meshes([tmp_path / name], ImportOptions(units="m", symmetry="none"))
        assert any(what in r for r in o.repairs), (name, o.repairs)
        assert o.model.mesh.is_watertight and o.model.mesh.volume > 0, name
    (o,) = import_meshes([tmp_path / "open_box.stl"], ImportOptions(units="m", symmetry="none"))
    assert o.model.mesh.volume == pytest.approx(0.08 * 0.05 * 0.03, rel=1e-6)  # the cap is the missing face


def test_meshes_that_cannot_be_objects_are_refused(tmp_path):
    grid = np.array([[x, y, 0.0] for y in range(3) for x in range(3)])
    quads = [(i + 3 * j, i + 1 + 3 * j, i + 4 + 3 * j, i + 3 + 3 * j) for j in range(2) for i in range(2)]
    faces = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    trimesh.Trimesh(grid, faces, process=False).export(tmp_path / "flat.ply")  # a sheet: no thickness
    trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], [[0, 1, 2], [1, 2, 3], [0, 2, 3], [0, 1, 3]],
                    process=False).export(tmp_path / "degenerate.ply")
    fin = C.box((0.05, 0.05, 0.05))  # a box with a fin: an edge shared by three faces
    v = np.vstack([fin.vertices, [[0.1, 0.1, 0.0]]])
    e = fin.edges_unique[0]
    trimesh.Trimesh(v, np.vstack([fin.faces, [[e[0], e[1], len(v) - 1]]]), process=False).export(tmp_path / "fin.ply")
    (tmp_path / "broken.stl").write_bytes(b"solid x\nfacet normal garbage\n")
    (tmp_path / "notes.txt").write_text("hello")
    for name, msg in [("flat.ply", "zero extent"), ("degenerate.ply", "degenerate"), ("fin.ply", "cannot close"),
                      ("broken.stl", "cannot read mesh|holds no triangle mesh"), ("notes.txt", "not a mesh file"),
                      ("missing.obj", "not found")]:
        with pytest.raises(ArgenError, match=msg):
            import_meshes([tmp_path / name], ImportOptions(units="m"))


def test_symmetry_none_and_file_override(tmp_path):
    src = _user_folder(tmp_path / "mine")
    (none_can, _) = import_meshes([src], ImportOptions(symmetry="none"))
    assert not none_can.model.symmetric
    f = tmp_path / "sym.json"
    flip = [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]  # BOP form, mm
    f.write_text(json.dumps({"widget": {"symmetries_discrete": [flip]}}))
    can, widget = import_meshes([src], ImportOptions(symmetry=str(f)))
    assert len(widget.model.info.symmetries_discrete) == 1 and "from" in widget.symmetry_note
    assert can.model.info.symmetries_continuous  # not listed in the file: searched
    f.write_text(json.dumps({"widget": {"symmetries_discrete": [[1, 2, 3]]}}))
    with pytest.raises(ArgenError, match="malformed symmetries"):
        import_meshes([src], ImportOptions(symmetry=str(f)))


def test_bop_folder_without_models_info_keeps_its_ids(tmp_path):
    d = tmp_path / "bop_models"
    d.mkdir()
    for o in builtin_objects(["mug", "duck"]):
        bop.write_mesh(d / f"obj_{o.obj_id:06d}.ply", o.mesh)
    objs, notes = load_any_models(d)
    assert [o.obj_id for o in objs] == [2, 4] and "imported" in notes[0]
    assert np.allclose(objs[0].info.bbox_size, builtin_objects(["mug"])[0].info.bbox_size, atol=1e-6)


def test_cli_import_and_capture_sim_with_a_plain_mesh_folder(tmp_path):
    src = _user_folder(tmp_path / "mine")
    res = runner.invoke(app, ["models", "import", str(src), "--out", str(tmp_path / "m")])
    assert res.exit_code == 0, res.output
    assert "symmetry: continuous" in res.output and "read as metres" in res.output
    res = runner.invoke(app, ["models", "import", str(src), "--out", str(tmp_path / "m"), "--units", "inch"])
    assert res.exit_code == 2 and res.output.count("\n") == 1 and "--units must be" in res.output
    out = tmp_path / "ds"
    res = runner.invoke(app, ["capture-sim", "--out", str(out), "--models", str(src), "--frames", "2",
                              "--objects", "widget", "--quiet"])
    assert res.exit_code == 0, res.output
    assert "not a BOP models folder" in res.output and "obj_000002 widget" in res.output
    assert json.loads((out / "models" / "names.json").read_text()) == {"2": "widget"}
    gts = [g for p in out.glob("train_pbr/*/scene_gt.json") for im in json.loads(p.read_text()).values() for g in im]
    assert gts and {g["obj_id"] for g in gts} == {2}
    objs, notes = load_any_models(src / "can.stl")  # one mesh file works too
    assert [o.name for o in objs] == ["can"] and "a mesh file" in notes[0]


def test_import_reports_a_mugs_part_symmetry(tmp_path):
    """The importer says what `argen label` will store: the mug's turns about its body (its handle the odd part)."""
    mug = builtin_objects(["mug"])[0]
    path = tmp_path / "mug.ply"
    mug.mesh.export(path)
    (o,) = import_meshes([path], ImportOptions(units="m"))
    assert "part symmetry: turns about (0.00, 0.00, 1.00)" in o.symmetry_note, o.symmetry_note
    C.cylinder(0.03, 0.1, sections=40).export(tmp_path / "can.stl")
    (can,) = import_meshes([tmp_path / "can.stl"], ImportOptions(units="m"))
    assert "continuous" in can.symmetry_note and "part symmetry" not in can.symmetry_note  # nothing to add
