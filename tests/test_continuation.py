"""The surface-continuation check (detector.geometry.verify.surface_continuation) on exact synthetic frames: a box
standing on a desk, and the same box's pose on part of a larger slab (a keyboard's edge), where every model point is
seen but the slab runs on past the box's outline in the plane of its face; and the surface samples with normals that
argen label writes for it."""

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from argen.h5 import LabelFile, write_label_file
from argen.label import object_table, sample_surface, sample_surface_normals
from argen.models.objects import builtin_objects
from detector.geometry.types import Detection, GeometryConfig, ObjectInfo
from detector.geometry.verify import continuation_checked, surface_continuation

F, C = 500.0, (160.0, 120.0)
BOX = (0.10, 0.08, 0.03)  # metres; its front face (towards the camera) 3 cm in front of the desk 1 m away
SLAB = (0.40, 0.14)  # the larger thing's front face, as wide and tall (metres), in the box's face plane


def depth_cloud(face: tuple[float, float]) -> np.ndarray:
    """(M,3) metres: a 320x240 depth image of a desk 1 m away with a face ``face`` (width, height metres) at 0.97 m
    centred on the optical axis."""
    v, u = np.mgrid[0:240, 0:320]
    x, y = (u + 0.5 - C[0]) / F, (v + 0.5 - C[1]) / F
    z = np.full(u.shape, 1.0)
    z[(np.abs(x * 0.97) < face[0] / 2) & (np.abs(y * 0.97) < face[1] / 2)] = 0.97
    return np.stack([x * z, y * z, z], axis=-1).reshape(-1, 3)


def box_objects() -> ObjectInfo:
    mesh = trimesh.creation.box(extents=BOX)
    pts, normals = sample_surface_normals(mesh.vertices, mesh.faces, 4000, np.random.default_rng(0))
    return ObjectInfo({1: np.zeros((9, 3))}, {1: float(np.linalg.norm(BOX))}, {1: pts[:1000]},
                      surfaces={1: (pts, normals)})


POSE = (np.eye(3), np.array([0.0, 0.0, 0.985]))  # the box's front face at 0.97 m, its back on the desk


def ratio(cloud: np.ndarray, objects: ObjectInfo, cfg=GeometryConfig()) -> tuple[int, int]:
    pts, normals = objects.surfaces[1]
    return surface_continuation(cloud, pts, normals, *POSE, cfg.continuation_tolerance,
                                cfg.continuation_reach * objects.diameters[1], 1.5 * objects.surface_spacing(1),
                                beyond=cfg.continuation_gap)


def test_a_real_box_explains_its_face_and_nothing_runs_on_past_it():
    explained, continued = ratio(depth_cloud(BOX[:2]), box_objects())
    assert explained > 250  # of the 1000 or so frame points counted in the box around it
    assert continued <= 0.01 * explained  # the desk beyond its outline is 3 cm behind the face's plane


def test_a_box_posed_on_part_of_a_larger_slab_has_the_slab_run_on_in_its_faces_plane():
    explained, continued = ratio(depth_cloud(SLAB), box_objects())
    real, _ = ratio(depth_cloud(BOX[:2]), box_objects())
    assert explained >= 0.95 * real  # every model point is seen, as for the real box: the depth check cannot tell
    assert continued > 0.5 * explained


def test_points_just_past_the_outline_are_not_counted_within_the_gap():
    """A face seen 7 mm wider on every side than the model's (the sensor's noise and blur at an outline) runs on
    within the gap only: nothing counted; without the gap it would be."""
    wider = (BOX[0] + 0.014, BOX[1] + 0.014)
    cfg = GeometryConfig()
    assert cfg.continuation_gap >= 0.01
    assert ratio(depth_cloud(wider), box_objects())[1] <= ratio(depth_cloud(BOX[:2]), box_objects())[1] + 2
    assert ratio(depth_cloud(wider), box_objects(), replace(cfg, continuation_gap=0.0))[1] > 25


def test_continuation_checked_lowers_only_the_pose_on_the_slab():
    objects = box_objects()
    cfg = GeometryConfig()
    det = Detection(1, 0.9, *POSE, 100, np.zeros((9, 3)), np.arange(3))
    kept = continuation_checked([det], depth_cloud(BOX[:2]), objects, cfg)[0]
    assert kept.score == det.score
    explained, continued = ratio(depth_cloud(SLAB), objects)
    lowered = continuation_checked([det], depth_cloud(SLAB), objects, cfg)[0]
    assert np.isclose(lowered.score, 0.9 * np.sqrt(cfg.continuation_limit / (continued / explained)))
    assert lowered.score < 0.2  # far under any model's min_score
    # an object without surface normals (a model whose table lacked them) is not checked
    bare = replace(objects, surfaces={})
    assert continuation_checked([det], depth_cloud(SLAB), bare, cfg)[0].score == det.score


def test_surface_samples_carry_their_faces_outward_normals():
    mesh = trimesh.creation.box(extents=BOX)
    pts, normals = sample_surface_normals(mesh.vertices, mesh.faces, 2000, np.random.default_rng(3))
    np.testing.assert_array_equal(pts, sample_surface(mesh.vertices, mesh.faces, 2000, np.random.default_rng(3)))
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    # on a box each point's normal is its face's axis, pointing away from the centre
    axis = np.argmax(np.abs(normals), axis=1)
    assert np.all(np.abs(normals[np.arange(len(pts)), axis]) > 1 - 1e-9)
    assert np.allclose(np.abs(pts[np.arange(len(pts)), axis]), np.asarray(BOX)[axis] / 2, atol=1e-9)
    assert np.all(np.sign(normals[np.arange(len(pts)), axis]) == np.sign(pts[np.arange(len(pts)), axis]))


def test_the_object_table_carries_surface_normals_through_a_label_file(tmp_path):
    objs = builtin_objects(["bottle", "duck"])
    table = object_table(objs, n_points=200, seed=1)
    for o, pts, normals in zip(sorted(objs, key=lambda o: o.obj_id), table.surface_points, table.surface_normals):
        assert pts.shape == normals.shape == (4000, 3)
        # outward normals: over a closed surface the flux of the position, area x mean(p . n), is 3 x its volume
        # (the divergence theorem); inward ones give minus that
        flux = o.mesh.area * np.mean(np.einsum("ij,ij->i", pts.astype(np.float64), normals))
        assert abs(flux / (3 * o.mesh.volume) - 1) < 0.05
    attrs = dict(created_by="test", source_dataset="synthetic", source_split="test", source_argen_json="",
                 max_points=500, max_depth=2.0, subsampling="voxel+random")
    path = write_label_file(tmp_path / "t.h5", attrs, table, [])
    with LabelFile(path) as lf:
        info = ObjectInfo.from_table(lf.objects)
    assert sorted(info.surfaces) == list(table.ids)
    for k, i in enumerate(table.ids):
        np.testing.assert_array_equal(info.surfaces[int(i)][1], table.surface_normals[k])


def test_predict_with_the_check_and_a_model_without_normals_warns_and_still_predicts(tmp_path):
    """A model trained before label files carried surface normals (checkpoints/ycbv3.pt without them): asked for
    the check, detector predict says that nothing is checked, and predicts the frame as before (exit 0, poses.json
    written)."""
    from pathlib import Path

    import cv2
    import torch
    from typer.testing import CliRunner

    from detector.cli.app import app as det_app

    payload = torch.load(Path(__file__).resolve().parents[1] / "checkpoints" / "ycbv3.pt", weights_only=True)
    objects = payload["stage1"]["objects"]
    payload["stage1"]["objects"] = {k: v for k, v in objects.items() if not k.startswith("surface_")}
    model = tmp_path / "old.pt"
    torch.save(payload, model)
    cv2.imwrite(str(tmp_path / "depth.png"), np.full((480, 640), 900, np.uint16))  # a wall 0.9 m away, mm
    args = ["predict", str(model), str(tmp_path / "depth.png"), "--K", "1066,1067,313,241", "--out"]
    r = CliRunner().invoke(det_app, [*args, str(tmp_path / "on")])  # the check is on by default
    assert r.exit_code == 0, r.output
    assert "continuation_check is on" in r.output and "nothing is checked" in r.output, r.output
    assert (tmp_path / "on" / "poses.json").is_file()
    r = CliRunner().invoke(det_app, [*args, str(tmp_path / "off"), "--set", "geometry.continuation_check=false"])
    assert r.exit_code == 0 and "continuation_check" not in r.output, r.output


def _model_file(path, table, with_surfaces: bool):
    """A two-stage model file's object table (no weights: add_surfaces reads and writes the dict only)."""
    import torch

    from detector.data.frames import object_table_dict
    from detector.training.checkpoint_file import FORMAT, TWO_STAGE_VERSION

    objects = object_table_dict(table)
    if not with_surfaces:
        objects = {k: v for k, v in objects.items() if not k.startswith("surface_")}
    torch.save({"format": FORMAT, "version": TWO_STAGE_VERSION, "stage1": {"objects": objects, "step": 7},
                "stage2": {"step": 3}, "extra": {"geometry_config": {"min_score": 0.65}}}, path)
    return path


def test_add_surfaces_gives_an_older_model_the_label_files_normals_and_changes_nothing_else(tmp_path):
    import torch

    from detector.checkpoint import add_surfaces
    from detector.errors import DetectorError

    table = object_table(builtin_objects(["bottle", "duck"]), n_points=200, seed=0)
    attrs = dict(created_by="test", source_dataset="synthetic", source_split="test", source_argen_json="",
                 max_points=500, max_depth=2.0, subsampling="voxel+random")
    label = write_label_file(tmp_path / "t.h5", attrs, table, [])
    old = _model_file(tmp_path / "old.pt", table, with_surfaces=False)
    assert ObjectInfo.from_table(torch.load(old, weights_only=True)["stage1"]["objects"]).surfaces == {}
    new = add_surfaces(old, label, tmp_path / "new.pt")
    before, after = torch.load(old, weights_only=True), torch.load(new, weights_only=True)
    info = ObjectInfo.from_table(after["stage1"]["objects"])
    for k, i in enumerate(table.ids):
        np.testing.assert_allclose(info.surfaces[int(i)][0], table.surface_points[k], atol=1e-7)
        np.testing.assert_allclose(info.surfaces[int(i)][1], table.surface_normals[k], atol=1e-7)
    assert {k: v for k, v in after["stage1"]["objects"].items() if not k.startswith("surface_")} \
        == before["stage1"]["objects"]
    assert after["stage2"] == before["stage2"] and after["extra"] == before["extra"]
    # another mesh of the same id (its diameter differs), or a label file without normals: refused, nothing written
    other = object_table(builtin_objects(["bottle", "duck"]), n_points=200, seed=0)
    other.diameters[0] *= 1.1
    bad = _model_file(tmp_path / "bad.pt", other, with_surfaces=False)
    with pytest.raises(DetectorError, match="not the same mesh"):
        add_surfaces(bad, label, tmp_path / "bad_out.pt")
    bare = replace(table, surface_points=[], surface_normals=[])
    with pytest.raises(DetectorError, match="no surface normals"):
        add_surfaces(old, write_label_file(tmp_path / "bare.h5", attrs, bare, []), tmp_path / "bare_out.pt")
    assert not (tmp_path / "bad_out.pt").exists() and not (tmp_path / "bare_out.pt").exists()
