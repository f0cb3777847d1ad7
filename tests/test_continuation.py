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


def test_the_surface_the_objects_stand_on_is_not_continued_unless_the_pose_lies_in_it():
    """A face in the plane of the table beside the model (a curved face meets it in its tangent plane) is not a pose
    on part of a larger thing: with the slab's points beside the box marked as the frame's support surface nothing
    is continued, with the desk's marked the slab still is. A pose the support surface itself explains (the whole
    slab marked: the box would lie in the table) is still checked."""
    objects, cfg = box_objects(), GeometryConfig()
    pts, normals = objects.surfaces[1]
    cloud = depth_cloud(SLAB)
    args = (cloud, pts, normals, *POSE, cfg.continuation_tolerance, cfg.continuation_reach * objects.diameters[1],
            1.5 * objects.surface_spacing(1), cfg.continuation_gap)
    explained, continued = surface_continuation(*args)
    assert continued > 0.5 * explained
    on_slab = cloud[:, 2] < 0.99
    beside = on_slab & ((np.abs(cloud[:, 0]) > BOX[0] / 2 + 0.005) | (np.abs(cloud[:, 1]) > BOX[1] / 2 + 0.005))
    assert surface_continuation(*args, support=beside) == (explained, 0)
    assert surface_continuation(*args, support=~on_slab) == (explained, continued)
    assert surface_continuation(*args, support=on_slab) == (explained, continued)

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


def test_a_surface_at_an_angle_crossing_the_faces_plane_is_not_continued():
    """Beside the box a ramp at 45 degrees crosses the plane of its front face 3 cm past its outline: the ramp's
    points there lie in the plane but on a surface at an angle to it (the table under an object, a neighbour
    leaning on it), so the normals' test counts none; without that test they would count."""
    v, u = np.mgrid[0:240, 0:320]
    xn, yn = ((u + 0.5 - C[0]) / F).ravel(), ((v + 0.5 - C[1]) / F).ravel()
    z = depth_cloud(BOX[:2])[:, 2].copy()
    ramp = (xn > 0.06) & (xn < 0.10) & (np.abs(yn) < 0.04)
    z[ramp] = 0.97 + (xn[ramp] - 0.08)  # metres; in the face's plane (0.97 m) at x = 0.08 m, the box ends at 0.05
    cloud = np.stack([xn * z, yn * z, z], axis=-1)
    objects, cfg = box_objects(), GeometryConfig()
    pts, normals = objects.surfaces[1]
    args = (cloud, pts, normals, *POSE, cfg.continuation_tolerance, cfg.continuation_reach * objects.diameters[1],
            1.5 * objects.surface_spacing(1), cfg.continuation_gap)
    assert surface_continuation(*args)[1] <= 1
    assert surface_continuation(*args, min_cos=-1.0)[1] > 10


def test_a_ratio_at_or_under_the_limit_keeps_the_score_and_few_points_continue_nothing():
    objects, cfg = box_objects(), GeometryConfig()
    det = Detection(1, 0.9, *POSE, 100, np.zeros((9, 3)), np.arange(3))
    wider = depth_cloud((BOX[0] + 0.018, BOX[1] + 0.018))  # 9 mm wider a side: a point or so past the gap, at corners
    explained, continued = ratio(wider, objects)
    assert 0 < continued / explained <= cfg.continuation_limit
    assert continuation_checked([det], wider, objects, cfg)[0].score == det.score
    pts, normals = objects.surfaces[1]
    two = np.array([[0.08, 0.0, 0.97], [0.09, 0.0, 0.97]])  # in the face's plane past its outline: no surface
    assert surface_continuation(two, pts, normals, *POSE, 0.005, 0.04, beyond=0.01) == (0, 0)


def test_estimate_checks_the_output_poses_and_the_unrefined_ones_only_where_they_count(monkeypatch):
    """Without ICP the unrefined poses are the output and are checked; with ICP only the refined ones, unless
    the caller reports both (detector eval: check_unrefined)."""
    import detector.infer as infer

    det = Detection(1, 0.9, *POSE, 100, np.zeros((9, 3)), np.arange(3))
    checked = []
    monkeypatch.setattr(infer, "detect", lambda *a, **k: [det])
    monkeypatch.setattr(infer, "refine", lambda dets, *a, **k: [replace(d, refined=True) for d in dets])

    def check(dets, cloud, objects, cfg, support):
        assert support.shape == (len(cloud),) and support.dtype == bool
        checked.append([d.refined for d in dets])
        return [replace(d, score=0.5 * d.score) for d in dets]

    monkeypatch.setattr(infer, "continuation_checked", check)
    preds = type("P", (), {"xyz": np.zeros((3, 3)), "obj_ids": np.ones(3, int), "confidence": np.ones(3),
                           "control_points": np.zeros((3, 9, 3))})()
    cfg = replace(GeometryConfig(), depth_check=False, colour_check=False, part_check=False, min_score=0.0,
                  min_score_unrefined=0.0)
    cloud = depth_cloud(BOX[:2])
    for icp, both, want in ((False, False, [[False]]), (True, False, [[True]]), (True, True, [[False], [True]])):
        checked.clear()
        unrefined, refined = infer.estimate(preds, box_objects(), replace(cfg, icp=icp), {}, cloud,
                                            check_unrefined=both)
        assert checked == want
        assert unrefined[0].score == (0.45 if want[0] == [False] else 0.9)
        assert refined is None if not icp else refined[0].score == 0.45
    checked.clear()
    infer.estimate(preds, box_objects(), replace(cfg, icp=True, continuation_check=False), {}, cloud)
    assert checked == []


def kinect_v1(cloud: np.ndarray, seed: int = 0) -> np.ndarray:
    """``cloud`` as a Kinect v1 at 1 m would see it: depth noise of 2.85 mm x z^2 (Khoshelham and Elberink 2012)
    and depth quantised to its disparity steps (an eighth of a pixel, 580 px focal length, 7.5 cm baseline: about
    2.9 mm at 1 m), each point moved along its ray."""
    rng = np.random.default_rng(seed)
    z = cloud[:, 2] + rng.normal(0.0, 0.00285 * cloud[:, 2] ** 2)
    disparity = np.round(8 * 580 * 0.075 / z) / 8  # pixels, to the eighth
    return cloud * ((580 * 0.075 / disparity) / cloud[:, 2])[:, None]


def test_a_kinect_v1s_noise_neither_lowers_the_real_box_nor_saves_the_pose_on_the_slab():
    """The check on the depth a real sensor gives: the box's own noisy points off its faces stay within the gap
    and the desk's stay out of its planes, so the real box keeps its score; the slab still runs on past it."""
    objects, cfg = box_objects(), GeometryConfig()
    det = Detection(1, 0.9, *POSE, 100, np.zeros((9, 3)), np.arange(3))
    for seed in range(3):
        assert continuation_checked([det], kinect_v1(depth_cloud(BOX[:2]), seed), objects, cfg)[0].score == det.score
        assert continuation_checked([det], kinect_v1(depth_cloud(SLAB), seed), objects, cfg)[0].score < 0.65


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
    in_place = _model_file(tmp_path / "in_place.pt", table, with_surfaces=False)
    assert add_surfaces(in_place, label) == in_place
    assert ObjectInfo.from_table(torch.load(in_place, weights_only=True)["stage1"]["objects"]).surfaces.keys() \
        == info.surfaces.keys()
    # a model of an object the label file lacks, or a stage-2 network alone: refused with a one-line message
    one = object_table(builtin_objects(["bottle"]), n_points=200, seed=0)
    with pytest.raises(DetectorError, match="is not in"):
        add_surfaces(old, write_label_file(tmp_path / "one.h5", attrs, one, []), tmp_path / "one_out.pt")
    from detector.training.checkpoint_file import FORMAT, TWO_STAGE_VERSION

    torch.save({"format": FORMAT, "version": TWO_STAGE_VERSION, "stage2": {"step": 3}}, tmp_path / "last.pt")
    with pytest.raises(DetectorError, match="stage-2 network only"):
        add_surfaces(tmp_path / "last.pt", label)
    bare = replace(table, surface_points=[], surface_normals=[])
    with pytest.raises(DetectorError, match="no surface normals"):
        add_surfaces(old, write_label_file(tmp_path / "bare.h5", attrs, bare, []), tmp_path / "bare_out.pt")
    assert not any((tmp_path / f).exists() for f in ("bad_out.pt", "bare_out.pt", "one_out.pt"))


def test_a_model_without_normals_takes_a_label_files_only_for_the_same_meshes():
    """detector eval gives a model trained before its table carried normals the label file's: only for objects it
    has, lacks normals for, and whose diameter is the label file's (the same mesh under the same id)."""
    label = box_objects()
    label.surfaces[2] = label.surfaces[1]
    label.diameters[2] = 0.2
    model = ObjectInfo({1: np.zeros((9, 3)), 2: np.zeros((9, 3)), 3: np.zeros((9, 3))},
                       {1: label.diameters[1], 2: 0.25, 3: 0.1}, {k: np.zeros((10, 3)) for k in (1, 2, 3)})
    assert model.take_surfaces(label) == [1]
    assert model.surfaces[1] is label.surfaces[1] and sorted(model.surfaces) == [1]
    assert model.take_surfaces(label) == []  # what it has stays
