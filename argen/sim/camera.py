"""Camera intrinsics and view sampling on the template's shell around the board.

OpenCV camera convention (x right, y down, z forward); ``T_cam_world`` maps world (= board frame,
z up) points into the camera.
"""

from __future__ import annotations

import numpy as np

from argen.config import CameraConfig


def intrinsics(cfg: CameraConfig) -> np.ndarray:
    """(3,3) pinhole matrix K in pixels."""
    return np.array([[cfg.fx, 0.0, cfg.cx], [0.0, cfg.fy, cfg.cy], [0.0, 0.0, 1.0]])


def look_at(position: np.ndarray, target: np.ndarray, azimuth: float, roll: float = 0.0) -> np.ndarray:
    """(4,4) T_cam_world of a camera at ``position`` looking at ``target`` (metres, world frame).

    The camera's x axis is horizontal (perpendicular to the azimuth direction), so the image is
    upright with world +z pointing up in the image, also when looking straight down; ``roll``
    (radians) then turns the camera about its optical axis.
    """
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    x = np.array([-np.sin(azimuth), np.cos(azimuth), 0.0])
    x -= z * (x @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    R_world_cam = np.stack([x, y, z], axis=1)
    T = np.eye(4)
    T[:3, :3] = R_world_cam.T
    T[:3, 3] = -R_world_cam.T @ np.asarray(position, float)
    return T


def sample_view(cfg: CameraConfig, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Sample a camera on the shell: distance, elevation and azimuth uniform in the template ranges.

    Returns T_cam_world (4,4) and the sampled parameters (metres, degrees) for the capture log.
    """
    d = rng.uniform(*cfg.distance)
    el = np.deg2rad(rng.uniform(*cfg.elevation_deg))
    az = np.deg2rad(rng.uniform(*cfg.azimuth_deg))
    target = np.array([*rng.normal(0.0, cfg.look_at_jitter, 2), 0.0])
    position = target + d * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    roll = np.deg2rad(rng.normal(0.0, cfg.roll_deg))
    T = look_at(position, target, az, roll)
    params = {"distance": float(d), "elevation_deg": float(np.rad2deg(el)), "azimuth_deg": float(np.rad2deg(az)),
              "roll_deg": float(np.rad2deg(roll)), "target": [float(v) for v in target]}
    return T, params
