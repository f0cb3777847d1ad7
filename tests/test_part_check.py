"""detector.geometry.part_check: a mug seen with its handle out of sight gets turned about its body to where the
frame's depth lets the handle hide; a mug whose handle is in sight, to where the frame sees it (exact synthetic
frames: the built-in mug in front of a wall, ray-cast)."""

import numpy as np
import open3d as o3d
import pytest
import trimesh

from argen.models.objects import builtin_objects
from argen.models.symmetry import find_part_symmetry, rotation_angle_axis
from detector.geometry.part_check import PART_SEEN, part_checked, part_turn
from detector.geometry.icp import turned_poses
from detector.geometry.types import Detection, GeometryConfig, ObjectInfo
from detector.geometry.verify import range_image

K = np.array([[525.0, 0, 160], [0, 525.0, 120], [0, 0, 1]])


@pytest.fixture(scope="module")
def mug():
    obj = builtin_objects(["mug"])[0]
    part = find_part_symmetry(obj.mesh, obj.diameter)
    pts = np.asarray(trimesh.sample.sample_surface(obj.mesh, 2000, seed=0)[0], np.float64)
    info = ObjectInfo({2: np.zeros((9, 3))}, {2: obj.diameter}, {2: pts}, part_symmetries={2: part.turns()},
                      odd_points={2: part.odd_points})
    return obj, part, info


def upright(handle_deg: float, part) -> tuple[np.ndarray, np.ndarray]:
    """The mug's pose 0.7 m in front of the camera, its axis along the camera's -y (upright), turned so that its
    handle points ``handle_deg`` degrees from the camera's +z (away from it) toward +x."""
    a = np.radians(handle_deg)
    # model x (the handle's side) -> (sin a, 0, cos a); model z (the axis) -> -y
    R = np.column_stack([[np.sin(a), 0, np.cos(a)], [np.cos(a), 0, -np.sin(a)], [0, -1, 0]])
    R[:, 1] = np.cross(R[:, 2], R[:, 0])
    t = np.array([0.0, 0.0, 0.7]) - R @ part.offset  # the axis passes 0.7 m ahead
    return R, t


def frame(obj, R, t) -> np.ndarray:
    """(M,3) metres: a 320x240 ray-cast depth image of the posed mug in front of a wall 1 m away."""
    scene = o3d.t.geometry.RaycastingScene()
    m = obj.mesh.copy().apply_transform(np.vstack([np.column_stack([R, t]), [0, 0, 0, 1]]))
    scene.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(m.faces, np.uint32)))
    v, u = np.mgrid[0:240, 0:320]
    d = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1).reshape(-1, 3)
    hit = scene.cast_rays(o3d.core.Tensor(np.hstack([np.zeros_like(d), d]).astype(np.float32)))["t_hit"].numpy()
    z = np.where(np.isfinite(hit), hit, 1.0)
    return d * np.minimum(z, 1.0)[:, None]


def turn_error_deg(R_true, R) -> float:
    return float(np.degrees(rotation_angle_axis(R_true.T @ R)[0]))


def checked(info, R, t, cloud, icp=False):
    d = Detection(2, 0.9, R, t, 10, np.zeros((9, 3)), np.arange(3))
    return part_checked([d], range_image(cloud), cloud, info, GeometryConfig(), icp=icp)[0]


@pytest.mark.parametrize("start", [60.0, 90.0, 150.0, -100.0])
def test_a_hidden_handle_is_turned_to_where_it_can_hide(mug, start):
    obj, part, info = mug
    R, t = upright(0.0, part)  # the handle straight behind the body
    cloud = frame(obj, R, t)
    Rs, ts = turned_poses(R, t, trimesh.transformations.rotation_matrix(np.radians(start), part.axis,
                                                                        part.offset)[None])
    got = checked(info, Rs[1], ts[1], cloud)
    assert turn_error_deg(R, Rs[1]) > 55 and turn_error_deg(R, got.R) < 25
    # a turn about the axis: the axis stays where it was
    assert np.linalg.norm((got.R @ part.offset + got.t) - (R @ part.offset + t)) < 1e-6


def test_a_handle_in_sight_is_turned_to_where_the_frame_sees_it(mug):
    obj, part, info = mug
    R, t = upright(90.0, part)  # the handle sideways, in profile
    cloud = frame(obj, R, t)
    Rs, ts = turned_poses(R, t, trimesh.transformations.rotation_matrix(np.radians(-130), part.axis,
                                                                        part.offset)[None])
    assert turn_error_deg(R, checked(info, Rs[1], ts[1], cloud).R) < 12
    # the right pose stays as it is
    same = checked(info, R, t, cloud)
    assert np.array_equal(same.R, R) and np.array_equal(same.t, t)


def test_objects_without_a_part_symmetry_are_left_alone(mug):
    obj, part, info = mug
    R, t = upright(0.0, part)
    cloud = frame(obj, R, t)
    plain = ObjectInfo(info.control_points, info.diameters, info.model_points)
    d = Detection(2, 0.9, R.T, t, 10, np.zeros((9, 3)), np.arange(3))
    assert part_checked([d], range_image(cloud), cloud, plain, GeometryConfig(), icp=False)[0] is d


def test_part_turn_picks_the_seen_turn_else_the_middle_of_the_allowed_run():
    n = 100
    through = np.full(12, 40)
    through[[3, 4, 5, 6, 7]] = [2, 0, 1, 0, 3]  # allowed: turns 3-7 (within the slack of the least)
    assert part_turn(np.zeros(12), through, n) == 5
    seen = np.zeros(12)
    seen[9] = (PART_SEEN + 0.05) * n + through[9]  # the odd part in sight under turn 9
    assert part_turn(seen, through, n) == 9
    wrap = np.full(12, 40)
    wrap[[9, 10, 11, 1, 2]] = 0  # turns on both sides of the pose, which the frame refuses
    wrap[0] = 30
    assert part_turn(np.zeros(12), wrap, n) == 10  # the middle of the longer run, 9-11
    wrap[0] = 0  # the pose itself allowed: kept, wherever it lies in its run
    assert part_turn(np.zeros(12), wrap, n) == 0
    assert part_turn(np.zeros(12), np.zeros(12), n) == 0  # nothing tells the turns apart: keep the pose
    two = np.full(12, 40)
    two[[1, 2]] = 0
    two[[6, 7, 8]] = 0
    assert part_turn(np.zeros(12), two, n) == 7  # the longer run
