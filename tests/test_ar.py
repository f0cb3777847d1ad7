"""Marker-based camera pose on synthetic images: the board texture warped by the plane homography.

No renderer: a view of the board plane z=0 from T_cam_board is the texture warped by
H = K [r1 r2 t] S, where S maps texture pixels to board metres (the documented texture convention).
"""

import cv2
import numpy as np
import pytest

from argen.config import ARConfig, BoardConfig
from argen.sim.ar import estimate_board_pose, implausible_pose, pose_error
from argen.sim.board import Board
from argen.sim.camera import look_at

K = np.array([[572.4114, 0, 325.2611], [0, 573.57043, 242.04899], [0, 0, 1]])  # LineMOD Kinect
GREY = 128


@pytest.fixture(scope="module")
def board():
    return Board.from_config(BoardConfig())


@pytest.fixture(scope="module")
def texture(board):
    return board.texture(1000)


def view(distance, elevation_deg, azimuth_deg, roll_deg=0.0, target=(0.0, 0.0)):
    """(4,4) T_cam_board of a camera on the shell looking at ``target`` on the board."""
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    tgt = np.array([*target, 0.0])
    pos = tgt + distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return look_at(pos, tgt, az, np.radians(roll_deg))


def synth(board, texture, T, rng, noise=3.0):
    """(480, 640, 3) uint8 RGB image of the board seen from T_cam_board on a grey background."""
    s = board.side / texture.shape[1]
    S = np.array([[s, 0, -board.side / 2 + 0.5 * s], [0, -s, board.side / 2 - 0.5 * s], [0, 0, 1]])
    H = K @ T[:3][:, [0, 1, 3]] @ S
    img = cv2.warpPerspective(texture, H, (640, 480), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=(GREY,) * 3)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    return np.clip(img + rng.normal(0, noise, img.shape), 0, 255).astype(np.uint8)


def project(board, T):
    """(M, 4, 2) pixel positions of every marker corner under T_cam_board."""
    c = board.marker_corners.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    return (c @ K.T)[:, :2].reshape(-1, 4, 2) / c[:, 2].reshape(-1, 4, 1)


VIEWS = [  # distance m, elevation deg, azimuth deg, roll deg, look-at target
    (0.6, 88, 10, 0, (0.0, 0.0)),
    (0.6, 40, 135, 4, (0.03, -0.02)),
    (0.75, 60, 250, -6, (-0.04, 0.01)),
    (0.9, 30, 300, 2, (0.0, 0.05)),
    (1.0, 70, 45, 8, (0.02, 0.02)),
    (1.1, 25, 190, -3, (-0.05, 0.0)),
    (1.1, 55, 80, 0, (0.0, 0.0)),
]


@pytest.mark.parametrize("i", range(len(VIEWS)))
def test_estimate_is_within_1deg_5mm(board, texture, i):
    d, el, az, roll, tgt = VIEWS[i]
    T = view(d, el, az, roll, tgt)
    est = estimate_board_pose(synth(board, texture, T, np.random.default_rng(i)), board, K, ARConfig())
    assert est.accepted, est.reason
    assert est.reason == "" and est.n_markers >= 4 and len(est.marker_ids) == est.n_markers
    assert set(est.marker_ids) <= set(board.marker_ids.tolist())
    rot, trans = pose_error(est.T_cam_board, T)
    assert rot < 1.0 and trans < 0.005, (rot, trans)
    assert 0 <= est.reproj_px < 2.0
    # the markers it reports are the ones whose projection lies inside the image
    # it reports only markers that are in the image, and most of those that are fully in it
    px = project(board, T)
    inside = np.flatnonzero(np.all((px >= 0) & (px <= [639, 479]), axis=(1, 2)))
    in_view = np.flatnonzero(np.all((px > -3) & (px < [642, 482]), axis=(1, 2)))
    assert set(est.marker_ids) <= set(in_view.tolist())
    assert est.n_markers >= 0.7 * len(inside)


def test_covered_markers_reject_the_frame(board, texture):
    T = view(0.8, 65, 30, 0)
    img = synth(board, texture, T, np.random.default_rng(10))
    assert estimate_board_pose(img, board, K, ARConfig()).accepted  # control: fine when uncovered
    px = project(board, T)
    covered = img.copy()
    for quad in px[3:]:  # paint over all markers but the first three (grown by a few pixels)
        centre = quad.mean(0)
        cv2.fillConvexPoly(covered, np.round(centre + 1.3 * (quad - centre)).astype(np.int32), (GREY,) * 3)
    est = estimate_board_pose(covered, board, K, ARConfig(min_markers=4))
    assert not est.accepted and est.T_cam_board is None
    assert est.n_markers <= 3 and "markers" in est.reason
    # with a looser threshold the three visible markers still give a good pose
    loose = estimate_board_pose(covered, board, K, ARConfig(min_markers=3))
    assert loose.accepted and sorted(loose.marker_ids) == [0, 1, 2]
    rot, trans = pose_error(loose.T_cam_board, T)
    assert rot < 1.5 and trans < 0.01


def test_reprojection_threshold_rejects_but_keeps_the_pose(board, texture):
    T = view(0.9, 45, 100, 0)
    img = synth(board, texture, T, np.random.default_rng(11), noise=6.0)
    est = estimate_board_pose(img, board, K, ARConfig(max_reproj_px=0.01))
    assert not est.accepted and "reprojection" in est.reason
    assert est.reproj_px > 0.01 and est.T_cam_board is not None
    assert pose_error(est.T_cam_board, T)[0] < 1.0


def test_foreign_markers_and_empty_images(board, texture):
    rng = np.random.default_rng(12)
    empty = np.clip(GREY + rng.normal(0, 5, (480, 640, 3)), 0, 255).astype(np.uint8)
    est = estimate_board_pose(empty, board, K, ARConfig())
    assert not est.accepted and est.T_cam_board is None and est.n_markers == 0 and "markers" in est.reason
    # a marker of the same dictionary that is not on the board is ignored
    T = view(0.7, 80, 0, 0)
    img = synth(board, texture, T, rng)
    foreign = cv2.aruco.generateImageMarker(board.dictionary, 90, 60)
    img[210:290, 290:370] = 255
    img[220:280, 300:360] = foreign[..., None]
    assert 90 in board.detector.detectMarkers(img)[1].ravel()
    est = estimate_board_pose(img, board, K, ARConfig())
    assert est.accepted and 90 not in est.marker_ids
    assert pose_error(est.T_cam_board, T)[0] < 1.0


def test_pose_error_known_offsets():
    T = view(0.8, 50, 20, 3)
    a = np.radians(7.0)
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    dR = cv2.Rodrigues(axis * a)[0]
    T2 = T.copy()
    T2[:3, :3] = dR @ T[:3, :3]
    T2[:3, 3] += [0.003, -0.004, 0.0]
    rot, trans = pose_error(T2, T)
    assert rot == pytest.approx(7.0, abs=1e-9) and trans == pytest.approx(0.005, abs=1e-12)
    assert pose_error(T, T) == pytest.approx((0.0, 0.0), abs=1e-6)
    assert pose_error(T2, T) == pytest.approx(pose_error(T, T2))


def test_implausible_poses_are_named(board):
    T = view(0.8, 50, 20, 3)
    assert implausible_pose(T, board) == ""
    below = T.copy()
    below[:3, :3] = T[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # board turned over about its x axis
    assert "below" in implausible_pose(below, board)
    behind = T.copy()
    behind[:3, 3] *= -1  # the mirror image of the board through the camera centre
    behind[:3, :3] = T[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    assert "behind" in implausible_pose(behind, board)
    straddling = T.copy()
    straddling[:3, 3] = [0.0, 0.0, 0.1]  # board plane along the optical axis, centre 10 cm ahead:
    straddling[:3, :3] = cv2.Rodrigues(np.array([np.pi / 2, 0, 0]))[0]  # its far half is behind the camera
    assert "behind" in implausible_pose(straddling, board)
