"""A printed box's way round: argen finds the turns its shape allows and carries its print (argen.models.texture,
the label file's object table); the detector turns a detection to the way round the frame's colours match
(detector.geometry.colour_check), under another camera's colours."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh

from argen.h5 import LabelFile, write_label_file
from argen.label import object_table
from argen.models.objects import ObjectModel, info_from_mesh, surface_scene
from argen.models.texture import shape_symmetries, surface_colours
from detector.data.frames import object_table_dict
from detector.geometry.colour_check import colour_checked
from detector.geometry.icp import turned_poses
from detector.geometry.types import Detection, GeometryConfig, ObjectInfo

EXTENTS = (0.09, 0.10, 0.03)  # metres, a gelatin-box-like print carrier
#: one colour per face pair of the box's six sides (-x, +x, -y, +y, -z, +z), RGB 0-255
FACE_RGB = np.array([[200, 30, 30], [240, 240, 230], [30, 40, 180], [250, 200, 20], [20, 150, 60], [120, 60, 20]])


def printed_box(rgb=FACE_RGB) -> trimesh.Trimesh:
    """A box whose six faces each have their own colour (vertex colours on unshared vertices), metres."""
    m = trimesh.creation.box(EXTENTS)
    m.unmerge_vertices()
    n = m.face_normals
    side = np.argmax(np.abs(n), axis=1) * 2 + (n[np.arange(len(n)), np.argmax(np.abs(n), axis=1)] > 0)
    vc = np.zeros((len(m.vertices), 4), np.uint8)
    vc[:, 3] = 255
    for f, s in zip(m.faces, side):
        vc[f, :3] = rgb[s]
    m.visual = trimesh.visual.ColorVisuals(m, vertex_colors=vc)
    return m


def box_object(rgb=FACE_RGB, symmetric=False) -> ObjectModel:
    m = printed_box(rgb)
    info = info_from_mesh(m, symmetries_discrete=[np.diag([-1.0, -1.0, 1.0, 1.0])] if symmetric else [])
    return ObjectModel(3, "box", m, info)


def face_colour(points: np.ndarray) -> np.ndarray:
    """The colour of the face each box surface point (N,3) model frame lies on, (N,3) 0-255."""
    rel = np.abs(points) / (np.array(EXTENTS) / 2)
    axis = np.argmax(rel, axis=1)
    return FACE_RGB[axis * 2 + (points[np.arange(len(points)), axis] > 0)]


def test_a_printed_box_has_three_half_turns_and_carries_its_print():
    obj = box_object()
    turns = shape_symmetries(obj)
    assert len(turns) == 3
    v = np.asarray(obj.mesh.vertices)
    for S in turns:  # each maps the box's corners onto its corners, and is a half turn (S S = I)
        moved = v @ S[:3, :3].T + S[:3, 3]
        assert np.abs(moved[:, None] - v[None]).sum(-1).min(axis=1).max() < 1e-6
        np.testing.assert_allclose(S @ S, np.eye(4), atol=1e-6)
    tab = object_table([obj])
    pts, cols = tab.texture_points[0], tab.texture_colours[0]
    assert len(pts) > 1000 and len(tab.shape_symmetries[0]) == 3
    d = surface_scene(obj.mesh).compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
    assert d.max() < 1e-6  # on the surface
    inner = np.sort(np.abs(pts) / (np.array(EXTENTS) / 2), axis=1)[:, 1] < 0.98  # away from the box's edges
    np.testing.assert_array_equal(cols[inner], face_colour(pts[inner]))  # each point has its face's colour


def test_no_print_or_listed_symmetries_carry_nothing():
    plain = object_table([box_object(rgb=np.tile([[150, 150, 150]], (6, 1)))])
    assert len(plain.shape_symmetries[0]) == 3 and len(plain.texture_points[0]) == 0
    assert ObjectInfo.from_table(object_table_dict(plain)).texture == {}  # nothing to choose by
    assert len(shape_symmetries(box_object(symmetric=True))) == 0  # its symmetries are its own: ADD-S handles them
    m = printed_box()
    m.visual = trimesh.visual.ColorVisuals(m)
    assert surface_colours(m, np.zeros((2, 3))) is None


def test_label_file_round_trip_keeps_the_print(tmp_path):
    tab = object_table([box_object()])
    path = write_label_file(tmp_path / "o.h5", dict(created_by="t", source_dataset="s", source_split="train",
                                                    source_argen_json="", max_points=10, max_depth=2.0,
                                                    subsampling="random"), tab, [])
    with LabelFile(path) as lf:
        o = lf.objects
        for a, b in ((o.shape_symmetries, tab.shape_symmetries), (o.texture_points, tab.texture_points),
                     (o.texture_colours, tab.texture_colours)):
            np.testing.assert_array_equal(a[0], b[0])
    info = ObjectInfo.from_table(object_table_dict(tab))
    assert set(info.texture) == {3} and info.texture[3][1].max() <= 1.0


def visible_points(info: ObjectInfo, R, t, rng, gains=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points of the box faces that face the camera, with their colours through a camera whose channel
    gains and noise differ from the model's: (N,3) metres, (N,3) in [0, 1]."""
    m = printed_box()
    p, f = trimesh.sample.sample_surface(m, 6000, seed=1)
    normals = m.face_normals[f] @ R.T
    cam = p @ R.T + t
    keep = np.einsum("ij,ij->i", normals, cam) < 0
    cols = np.clip(face_colour(p[keep]) / 255.0 * np.asarray(gains) + rng.normal(0, 0.03, (keep.sum(), 3)), 0, 1)
    return cam[keep] + rng.normal(0, 0.0005, (keep.sum(), 3)), cols


@pytest.mark.parametrize("icp", [False, True])
def test_a_box_posed_the_wrong_way_round_is_turned_back_under_another_cameras_colours(icp):
    rng = np.random.default_rng(0)
    info = ObjectInfo.from_table(object_table_dict(object_table([box_object()])))
    R = trimesh.transformations.euler_matrix(0.6, -0.4, 0.3)[:3, :3]  # three faces in view
    t = np.array([0.02, -0.01, 0.6])
    cloud, colours = visible_points(info, R, t, rng, gains=(0.7, 1.1, 1.3))
    cfg = GeometryConfig(icp=icp)
    Rk, tk = turned_poses(R, t, info.shape_symmetries[3])
    dets = [Detection(3, 0.9, Rk[k], tk[k], 10, np.zeros((9, 3)), np.arange(3), points=np.arange(len(cloud)))
            for k in range(len(Rk))]
    out = colour_checked(dets, cloud, colours, info, cfg, icp=icp)
    for d in out:  # every way round, the right one included, comes back as the right one
        angle = np.degrees(np.arccos(np.clip((np.trace(d.R.T @ R) - 1) / 2, -1, 1)))
        assert angle < 1.0 and np.linalg.norm(d.t - t) < 1e-3, (angle, d.t - t)
    # without colour (a depth-only frame) or without the detection's points, nothing is turned
    same = colour_checked(dets, cloud, np.zeros_like(colours), info, cfg, icp=icp)
    assert all(np.allclose(a.R, b.R) for a, b in zip(same, dets))
    no_pts = [Detection(3, 0.9, Rk[1], tk[1], 10, np.zeros((9, 3)), np.arange(3))]
    assert np.allclose(colour_checked(no_pts, cloud, colours, info, cfg, icp=icp)[0].R, Rk[1])


def test_a_stage_2_without_colour_learns_the_printed_box_up_to_its_shape_turns():
    """A crop network that sees no colour cannot tell the turns apart that only the print breaks: its training
    targets include the coordinates under each turn (identity first), every target set maps the box onto itself,
    and the loss of a prediction made in the turned pose is zero for it, where a colour-input stage 2 is taught the
    one pose (an object listed symmetric keeps its own symmetries)."""
    import torch

    from detector.stage2.crops import shape_only_symmetries, symmetry_targets
    from detector.stage2.network import crop_loss

    obj = box_object()
    turns = shape_symmetries(obj)
    S = shape_only_symmetries(np.eye(4)[None], turns)
    assert S.shape == (4, 4, 4) and np.allclose(S[0], np.eye(4))
    v = np.asarray(obj.mesh.vertices)
    for T in S:
        moved = v @ T[:3, :3].T + T[:3, 3]
        assert np.abs(moved[:, None] - v[None]).sum(-1).min(axis=1).max() < 1e-6
    own = np.stack([np.eye(4), np.diag([-1.0, -1.0, 1.0, 1.0])])
    assert np.allclose(shape_only_symmetries(own, np.zeros((0, 4, 4))), own)
    dia = obj.diameter
    x = np.random.default_rng(0).uniform(-0.5, 0.5, (64, 3)) * np.array(EXTENTS) / dia  # model coordinates, diameters
    turned = symmetry_targets(x, turns[1:2], dia)[0]  # what the points read in the box turned half way
    pred = {"fg_logit": torch.full((1, 64), 10.0), "coords": torch.from_numpy(turned[None])}
    fg = torch.ones(1, 64)
    for sym, zero in ((S, True), (np.eye(4)[None].astype(np.float32), False)):
        coords = torch.from_numpy(symmetry_targets(x, sym, dia)[None])
        coord = float(crop_loss(pred, fg, coords, torch.ones(1, len(sym), dtype=torch.bool))[1]["coord"])
        assert (coord < 1e-9) == zero, coord


def test_older_stage_2_runs_resume_with_the_symmetries_they_were_taught():
    """A stage-2 run saved before ``crop.shape_turns`` existed reads it as it was trained: a colour-free one without
    the turns (it was taught its own symmetries only), any other with the default; and a label file's printed box
    gets the turns in a colour-free dataset only while the setting is on."""
    from dataclasses import asdict

    from detector.stage2.crops import CropConfig
    from detector.stage2.dataset import crop_symmetries
    from detector.stage2.train import Stage2TrainConfig, saved_settings

    for colour, turns in (("none", False), ("light", True)):
        old = asdict(Stage2TrainConfig())
        del old["crop"]["shape_turns"]
        old["crop"]["colour"] = colour
        assert saved_settings(old)["crop"]["shape_turns"] is turns
        assert saved_settings(old)["crop"]["colour"] == colour
    table = object_table_dict(object_table([box_object()]))
    sizes = {(c, t): len(crop_symmetries(table, CropConfig(colour=c, shape_turns=t))[3])
             for c in ("none", "camera") for t in (True, False)}
    assert sizes == {("none", True): 4, ("none", False): 1, ("camera", True): 1, ("camera", False): 1}


def test_what_reads_colour_is_each_colour_input_and_the_check_where_a_print_is_carried():
    """detector predict warns about a frame without colour when anything of the model reads colour: either
    network's colour input, or the colour check for a model whose objects carry a print."""
    from types import SimpleNamespace

    from detector.infer import colour_networks, colour_readers

    def model(s1, s2):
        return SimpleNamespace(normalisation={"colour": s1}, stage2={"normalisation": {"colour": s2}})

    printed = ObjectInfo.from_table(object_table_dict(object_table([box_object()])))
    plain = ObjectInfo.from_table(object_table_dict(object_table([box_object(rgb=np.tile([[150] * 3], (6, 1)))])))
    on, off = GeometryConfig(colour_check=True), GeometryConfig(colour_check=False)
    assert colour_readers(model("none", "none"), printed, on) == ["the colour check"]
    assert colour_readers(model("none", "none"), printed, off) == []
    assert colour_readers(model("none", "none"), plain, on) == []
    assert colour_readers(model("grey_world", "light"), plain, on) == ["stage 1", "stage 2"]
    assert colour_readers(model("none", "camera"), printed, on) == ["stage 2", "the colour check"]
    single = SimpleNamespace(normalisation={"colour": "light"}, stage2=None)
    assert colour_readers(single, plain, off) == ["stage 1"]
    # the networks alone, whatever the objects and the check
    assert colour_networks(model("none", "camera")) == ["stage 2"] and colour_networks(model("none", "none")) == []
    assert colour_networks(model("grey_world", "none")) == ["stage 1"] and colour_networks(single) == ["stage 1"]


@pytest.mark.parametrize("ckpt, readers, cost", [
    ("lm8.pt", "stage 1, stage 2", "it finds little without it"),
    ("ycbv3.pt", "the colour check", "a printed object's way round is left unchecked"),
])
def test_predict_warns_about_a_frame_without_colour_with_what_the_model_loses(tmp_path, ckpt, readers, cost):
    """A depth PNG given without its colour image: the shipped model whose networks read colour warns that it finds
    little; the one whose networks see geometry only, and whose objects carry a print, warns that the print's check
    is skipped. Either way the frame is still predicted (exit 0, poses.json written)."""
    import cv2
    from typer.testing import CliRunner

    from detector.cli.app import app as det_app

    model = Path(__file__).resolve().parents[1] / "checkpoints" / ckpt
    depth = np.full((480, 640), 900, np.uint16)  # a wall 0.9 m away, millimetres
    cv2.imwrite(str(tmp_path / "depth.png"), depth)
    r = CliRunner().invoke(det_app, ["predict", str(model), str(tmp_path / "depth.png"), "--K", "572,573,325,242",
                                     "--out", str(tmp_path / "pred")])
    assert r.exit_code == 0, r.output
    assert f"reads colour ({readers})" in r.output and cost in r.output, r.output
    assert (tmp_path / "pred" / "poses.json").is_file()
