"""detector.geometry.verify: the depth check on an exact synthetic frame (a box standing out of a wall)."""

import numpy as np
import pytest
import trimesh

from detector.geometry.types import Detection, GeometryConfig, ObjectInfo
from detector.geometry.verify import depth_checked, depth_consistency, range_image

K = np.array([[500.0, 0, 160], [0, 500.0, 120], [0, 0, 1]])
SIZE = (0.10, 0.08, 0.05)  # the box, metres: its front face 5 cm in front of a wall 1 m away


def frame_cloud(keep: float, seed: int = 0) -> np.ndarray:
    """(M,3) metres: a 320x240 depth image of the wall with the box's front face, a random ``keep`` share of it."""
    v, u = np.mgrid[0:240, 0:320]
    x, y = (u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1]
    z = np.full(u.shape, 1.0)
    face = (np.abs(x * 0.95) < SIZE[0] / 2) & (np.abs(y * 0.95) < SIZE[1] / 2)
    z[face] = 0.95
    pts = np.stack([x * z, y * z, z], axis=-1).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    return pts[rng.random(len(pts)) < keep]


def box_points(size, n: int = 1000) -> np.ndarray:
    return np.asarray(trimesh.creation.box(extents=size).sample(n, seed=1), np.float64)


def consistency(cloud, size, t, R=np.eye(3)):
    return depth_consistency(range_image(cloud), box_points(size), R[None], np.asarray(t, float)[None], 0.004, 0.008)[0]


@pytest.mark.parametrize("keep", [0.05, 0.3, 1.0])
def test_the_right_pose_is_consistent_at_any_cloud_density(keep):
    cloud = frame_cloud(keep)
    assert consistency(cloud, SIZE, [0, 0, 0.975]) > 0.95
    # the cell follows the points' spacing: every frame point finds a depth no farther than its own
    ri = range_image(cloud)
    z = ri.lookup(cloud)
    assert np.all(np.isfinite(z)) and np.all(z <= cloud[:, 2] + 1e-12)


def test_poses_the_sensor_sees_past_are_not():
    cloud = frame_cloud(0.3)
    right = consistency(cloud, SIZE, [0, 0, 0.975])
    bigger = consistency(cloud, (0.2, 0.16, 0.05), [0, 0, 0.975])  # explains every face point, but the wall shows
    beside = consistency(cloud, SIZE, [0.07, 0, 0.975])  # half of it floats in front of the wall
    assert right > 0.95 and bigger < 0.4 and beside < 0.6
    # hidden behind the wall: no model point is seen or seen past
    assert consistency(cloud, SIZE, [0, 0, 1.2]) == 0.0
    # turned so a 5 cm side faces the camera: its front is 2.5 cm behind the face it claims to be
    turned = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    assert consistency(cloud, SIZE, [0, 0, 0.975], turned) < 0.5


def test_depth_checked_keeps_consistent_scores_and_scales_the_others():
    cloud = frame_cloud(0.3)
    pts = box_points(SIZE)
    objs = ObjectInfo({1: np.zeros((9, 3))}, {1: float(np.linalg.norm(SIZE))}, {1: pts})
    cfg = GeometryConfig(support_distance=0.02, support_floor=0.004, depth_tolerance=2.0, depth_consistent=0.85)
    dets = [Detection(1, 0.8, np.eye(3), np.array(t), 10, np.zeros((9, 3)), np.arange(3))
            for t in ([0, 0, 0.975], [0.07, 0, 0.975])]
    ri = range_image(cloud)
    out = depth_checked(dets, ri, objs, cfg)
    right, beside = (depth_consistency(ri, pts, d.R[None], d.t[None], 0.008, 0.016)[0] for d in dets)
    assert right >= 0.85 and out[0].score == 0.8  # consistent enough: the score stays
    assert beside < 0.85 and out[1].score == pytest.approx(0.8 * beside / 0.85)
    assert np.array_equal(out[1].t, dets[1].t) and out[1].score < 0.6


def test_an_empty_cloud_checks_nothing():
    ri = range_image(np.zeros((0, 3)))
    assert depth_consistency(ri, box_points(SIZE), np.eye(3)[None], np.array([[0, 0, 1.0]]), 0.004, 0.008)[0] == 0


def test_refined_poses_can_be_held_to_a_stricter_consistency():
    cloud = frame_cloud(0.3)
    pts = box_points(SIZE)
    objs = ObjectInfo({1: np.zeros((9, 3))}, {1: float(np.linalg.norm(SIZE))}, {1: pts})
    ri = range_image(cloud)
    # a pose 4 mm beside the box: most of it on the face, an edge strip floating in front of the wall
    det = Detection(1, 0.9, np.eye(3), np.array([0.004, 0, 0.975]), 10, np.zeros((9, 3)), np.arange(3))
    c = depth_consistency(ri, pts, det.R[None], det.t[None], 0.008, 0.016)[0]
    assert 0.85 <= c < 0.97
    loose = GeometryConfig(support_distance=0.02, support_floor=0.004, depth_tolerance=2.0, depth_consistent=0.85)
    strict = GeometryConfig(**{**vars(loose), "depth_consistent_refined": 0.97})
    # unset: the refined poses are checked as the others; set: only the refined ones are held to it
    assert depth_checked([det], ri, objs, loose, refined=True)[0].score == 0.9
    assert depth_checked([det], ri, objs, strict)[0].score == 0.9
    assert depth_checked([det], ri, objs, strict, refined=True)[0].score == pytest.approx(0.9 * c / 0.97)
    right = Detection(1, 0.9, np.eye(3), np.array([0, 0, 0.975]), 10, np.zeros((9, 3)), np.arange(3))
    assert depth_checked([right], ri, objs, strict, refined=True)[0].score == 0.9  # the right pose keeps its score
