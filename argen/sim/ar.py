"""Marker-based camera pose: detect the board's ArUco markers in an RGB image and solve for T_cam_board.

This is the AR step of a capture: the virtual objects are rendered from this *estimated* pose, as a
real AR capture would, and a frame is only kept when the estimate is trustworthy (enough markers,
small reprojection error, board in front of the camera and facing it), as the paper filtered frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from argen.config import ARConfig
from argen.sim.board import Board


@dataclass
class PoseEstimate:
    """Result of :func:`estimate_board_pose`.

    T_cam_board: (4, 4) float64 board-to-camera pose (metres), or None when no pose could be solved;
    it is also set for rejected estimates (so the caller can log their error). n_markers: board markers
    detected; marker_ids: their ids; reproj_px: RMS reprojection error of the used corners (pixels,
    nan when unsolved); accepted: whether the pose passes the ARConfig checks; reason: why not ("" if so).
    """

    T_cam_board: np.ndarray | None
    n_markers: int
    marker_ids: list[int] = field(default_factory=list)
    reproj_px: float = float("nan")
    accepted: bool = False
    reason: str = ""


def _to_gray(rgb: np.ndarray) -> np.ndarray:
    img = np.asarray(rgb)
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


def _pose_matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).ravel()
    return T


def detect_markers(rgb: np.ndarray, board: Board) -> tuple[np.ndarray, np.ndarray]:
    """Detect the board's markers (sub-pixel corners), keeping only ids that belong to the board.

    rgb: (H, W, 3) uint8 RGB (or (H, W) grey). Returns corners (K, 4, 2) float32 pixels in cv2.aruco
    order and ids (K,) int32, one entry per distinct board marker.
    """
    corners, ids, _ = board.detector.detectMarkers(_to_gray(rgb))
    if ids is None or len(ids) == 0:
        return np.zeros((0, 4, 2), np.float32), np.zeros(0, np.int32)
    corners = np.asarray(corners, np.float32).reshape(-1, 4, 2)
    ids = ids.ravel().astype(np.int32)
    keep = np.isin(ids, board.marker_ids)
    _, first = np.unique(ids, return_index=True)  # a duplicated id is ambiguous: keep its first sighting
    keep &= np.isin(np.arange(len(ids)), first)
    return corners[keep], ids[keep]


def estimate_board_pose(rgb: np.ndarray, board: Board, K: np.ndarray, cfg: ARConfig,
                        dist: np.ndarray | None = None) -> PoseEstimate:
    """Estimate T_cam_board from the markers visible in ``rgb`` and decide whether to accept it.

    rgb: (H, W, 3) uint8 RGB. K: (3, 3) intrinsics, pixels. dist: OpenCV distortion coefficients or
    None (no distortion). PnP: IPPE (both planar solutions, the better one) refined with
    Levenberg-Marquardt on all matched corners.
    """
    K = np.asarray(K, np.float64)
    dist = np.zeros(5) if dist is None else np.asarray(dist, np.float64)
    corners, ids = detect_markers(rgb, board)
    n, id_list = len(ids), [int(i) for i in ids]
    if n == 0 or n < cfg.min_markers:
        return PoseEstimate(None, n, id_list, reason=f"only {n} markers detected (need {cfg.min_markers})")
    obj, img = board.cv_board.matchImagePoints(list(corners[:, None]), ids.reshape(-1, 1))
    obj = np.asarray(obj, np.float64).reshape(-1, 3)
    img = np.asarray(img, np.float64).reshape(-1, 2)
    ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok or len(rvecs) == 0:
        return PoseEstimate(None, n, id_list, reason="PnP failed on the detected markers")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvecs[0].copy(), tvecs[0].copy())
    proj = cv2.projectPoints(obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
    reproj = float(np.sqrt(np.mean(np.sum((proj - img) ** 2, axis=1))))
    T = _pose_matrix(rvec, tvec)
    est = PoseEstimate(T, n, id_list, reproj, accepted=False)
    problem = implausible_pose(T, board)
    if problem:
        est.reason = problem
    elif reproj > cfg.max_reproj_px:
        est.reason = f"reprojection error {reproj:.2f} px above {cfg.max_reproj_px:g} px ({n} markers)"
    else:
        est.accepted = True
    return est


def implausible_pose(T_cam_board: np.ndarray, board: Board) -> str:
    """Why a board pose cannot be what a camera saw ("" when it can).

    T_cam_board: (4, 4), metres. The board must lie in front of the camera (every marker corner at
    z > 0) and show its top side (the board normal pointing towards the camera centre).
    """
    T = np.asarray(T_cam_board, np.float64)
    corners_cam = board.marker_corners.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    if (corners_cam[:, 2] <= 0).any():
        return "pose puts the board behind the camera"
    if T[:3, 2] @ -T[:3, 3] <= 0:  # normal in camera frame . (board origin -> camera centre)
        return "pose shows the board from below"
    return ""


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Rotation angle (degrees) and translation distance (metres) between two (4, 4) poses."""
    R = np.asarray(T_est)[:3, :3].T @ np.asarray(T_true)[:3, :3]
    sin = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    cos = (np.trace(R) - 1.0) / 2.0
    trans = float(np.linalg.norm(np.asarray(T_est)[:3, 3] - np.asarray(T_true)[:3, 3]))
    return float(np.degrees(np.arctan2(sin, cos))), trans
