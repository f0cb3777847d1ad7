"""Unregistered RealSense bags (RealSense Viewer's raw depth and colour streams): argen.real.bag registers the depth
to the colour camera from the bag's own camera_info and tf extrinsics.

The synthetic bag is laid out as librealsense writes one (topics, mono16 depth, ``Depth_Units`` option, a
reference -> stream ``geometry_msgs/Transform`` per stream; see argen/real/bag.py). Its scene is analytic: a slanted
wall and a box in front of it, ray-cast from each camera, so the depth the colour camera sees is known exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import maximum_filter, minimum_filter

from argen.errors import ArgenError
from argen.real.bag import register_depth
from argen.real.readers import open_any

WD, HD = 320, 240  # the depth stream: wider field of view, fewer pixels (as a D435's)
K_DEPTH = np.array([[300.0, 0.0, 158.7], [0.0, 301.0, 121.2], [0.0, 0.0, 1.0]])
WC, HC = 400, 300  # the colour stream
K_COLOUR = np.array([[410.0, 0.0, 201.3], [0.0, 409.0, 148.9], [0.0, 0.0, 1.0]])
UNITS = 0.0001  # metres per depth unit (the bag's Depth_Units option)
WALL = (np.array([0.0, 0.0, 1.25]), np.radians([8.0, -4.0]))  # a point on it, its tilt about y and x
BOX = (np.array([-0.12, -0.05, 0.85]), np.array([0.06, 0.10, 1.0]))  # min and max corner, depth camera frame


def _rotation(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    S = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * S + (1 - np.cos(angle)) * S @ S


def _pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


# depth -> colour: a 15 mm baseline and a third of a degree of rotation (a D400's colour camera sits like this)
DEPTH_TO_COLOUR = _pose(_rotation([0.3, 1.0, 0.2], 0.006), [0.015, 0.0003, -0.0004])


def _scene_depth(T_cam_from_depth: np.ndarray, K: np.ndarray, w: int, h: int) -> np.ndarray:
    """(h, w) metres: the z, in the camera's frame, of the nearest scene surface along each pixel's ray (0: none).
    T_cam_from_depth maps depth-frame points into that camera's frame."""
    T = np.linalg.inv(T_cam_from_depth)  # the camera in the depth frame, where the scene is defined
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    d, o = rays @ T[:3, :3].T, T[:3, 3]  # ray s has camera z = s (its direction has z = 1 in the camera)
    point, (ay, ax) = WALL
    n = np.array([np.sin(ay), np.sin(ax), -np.cos(ay) * np.cos(ax)])
    with np.errstate(divide="ignore", invalid="ignore"):
        s_wall = ((point - o) @ n) / (d @ n)
        s0, s1 = (BOX[0] - o) / d, (BOX[1] - o) / d
    near, far = np.minimum(s0, s1).max(axis=1), np.maximum(s0, s1).min(axis=1)
    s_box = np.where((near <= far) & (near > 0), near, np.inf)
    s = np.minimum(np.where(s_wall > 0, s_wall, np.inf), s_box)
    return np.where(np.isfinite(s), s, 0.0).reshape(h, w)


def _quaternion(R: np.ndarray) -> np.ndarray:
    """(x, y, z, w) of a rotation matrix (small rotations: w > 0), negated as librealsense's rot2quat writes it."""
    w = np.sqrt(1.0 + np.trace(R)) / 2
    q = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (4 * w)
    return -np.array([*q, w])


def _write_realsense_bag(path: Path, depth_m: np.ndarray, rgb: np.ndarray, tf: dict | None, frames: int = 2):
    """A bag as RealSense Viewer records one: raw Depth_0 (sensor_0) and Color_0 (sensor_1) streams with their
    camera_info, the Depth_Units option, and ``tf``: {"Depth_0": T, "Color_0": T}, reference -> stream."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    t = ts.types
    Image, Info, Header, Time = (t["sensor_msgs/msg/Image"], t["sensor_msgs/msg/CameraInfo"],
                                 t["std_msgs/msg/Header"], t["builtin_interfaces/msg/Time"])
    Float32, Transform, Vector3, Quaternion = (t["std_msgs/msg/Float32"], t["geometry_msgs/msg/Transform"],
                                               t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Quaternion"])
    RoI = t["sensor_msgs/msg/RegionOfInterest"]
    streams = {"Depth_0": "/device_0/sensor_0/Depth_0", "Color_0": "/device_0/sensor_1/Color_0"}

    def conn(w, topic, cls):
        return w.add_connection(topic, cls.__msgtype__, typestore=ts)

    with Writer(path) as w:
        c_units = conn(w, "/device_0/sensor_0/option/Depth_Units/value", Float32)
        w.write(c_units, 1, ts.serialize_ros1(Float32(data=UNITS), Float32.__msgtype__))
        for name, T in (tf or {}).items():
            q = _quaternion(T[:3, :3])
            msg = Transform(translation=Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                            rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))
            w.write(conn(w, streams[name] + "/tf/0", Transform), 1, ts.serialize_ros1(msg, Transform.__msgtype__))
        images = {}
        for name, K, (h, w_) in (("Depth_0", K_DEPTH, depth_m.shape), ("Color_0", K_COLOUR, rgb.shape[:2])):
            hdr = Header(seq=0, stamp=Time(sec=1, nanosec=0), frame_id="0")
            info = Info(header=hdr, height=h, width=w_, distortion_model="Brown Conrady", D=np.zeros(5),
                        K=K.reshape(-1), R=np.zeros(9), P=np.zeros(12), binning_x=0, binning_y=0,
                        roi=RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
            w.write(conn(w, streams[name] + "/info/camera_info", Info), 1, ts.serialize_ros1(info, Info.__msgtype__))
            images[name] = conn(w, streams[name] + "/image/data", Image)
        raw = np.round(depth_m / UNITS).astype("<u2")
        for k in range(frames):
            ns = 1_000_000_000 + k * 33_333_333
            hdr = Header(seq=k, stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="0")
            msg = Image(header=hdr, height=HD, width=WD, encoding="mono16", is_bigendian=0, step=WD * 2,
                        data=raw.view(np.uint8).reshape(-1))
            w.write(images["Depth_0"], ns, ts.serialize_ros1(msg, Image.__msgtype__))
            msg = Image(header=hdr, height=HC, width=WC, encoding="rgb8", is_bigendian=0, step=WC * 3,
                        data=np.ascontiguousarray(rgb).reshape(-1))
            w.write(images["Color_0"], ns + 1_000_000, ts.serialize_ros1(msg, Image.__msgtype__))


@pytest.fixture(scope="module")
def scene():
    """(depth seen by the depth camera, expected depth in the colour camera, rgb), metres."""
    depth = _scene_depth(np.eye(4), K_DEPTH, WD, HD)
    expected = _scene_depth(DEPTH_TO_COLOUR, K_COLOUR, WC, HC)
    rgb = np.zeros((HC, WC, 3), np.uint8)
    rgb[..., 0] = np.arange(WC) % 256
    return depth, expected, rgb


@pytest.mark.parametrize("reference", ["depth", "colour"])
def test_unregistered_bag_is_registered_to_the_colour_camera(scene, tmp_path, reference):
    depth, expected, rgb = scene
    # librealsense stores reference -> stream; the reference is depth on a D400, but any stream of the group may be
    tf = ({"Depth_0": np.eye(4), "Color_0": DEPTH_TO_COLOUR} if reference == "depth"
          else {"Depth_0": np.linalg.inv(DEPTH_TO_COLOUR), "Color_0": np.eye(4)})
    _write_realsense_bag(tmp_path / "rs.bag", depth, rgb, tf)
    rec = open_any(tmp_path / "rs.bag")
    assert (rec.width, rec.height) == (WC, HC) and np.allclose(rec.K, K_COLOUR)
    assert rec.depth_scale == pytest.approx(UNITS * 1000)  # mm per unit, from the Depth_Units option
    assert np.allclose(rec.registration.depth_to_colour, DEPTH_TO_COLOUR, atol=1e-6)
    assert len(rec) == 2
    r, d = rec.read(1)
    assert np.array_equal(r, rgb) and d.shape == (HC, WC) and d.dtype == np.float32

    # away from the box's outline and its steep sides, every pixel both cameras see is registered, within 1 mm
    smooth = (maximum_filter(expected, 5) - minimum_filter(expected, 5)) < 0.01
    err = np.abs(d - expected)
    valid = (d > 0) & smooth
    assert valid.sum() > 0.85 * HC * WC
    assert err[valid].max() < 0.001, err[valid].max()
    # the wall the depth camera sees behind the box lands inside the box's image: the nearer box must win there
    box = smooth & (expected < 1.0)
    assert box.sum() > 3000 and (d[box] > 0).all() and err[box].max() < 0.001
    # holes only where the depth camera cannot see: the wall hidden behind the box from the depth camera's side
    holes = smooth & (d == 0) & (expected > 0)
    assert holes.sum() < 0.03 * HC * WC
    edge = (d > 0) & ~smooth  # at the outline: a depth of the surfaces around the pixel, nothing invented
    assert (d[edge] > minimum_filter(expected, 5)[edge] - 0.001).all()
    assert (d[edge] < maximum_filter(expected, 5)[edge] + 0.001).all()

    # the test tells the directions apart: the transform taken the other way round is centimetres off
    wrong = register_depth(depth.astype(np.float32), K_DEPTH, K_COLOUR, np.linalg.inv(DEPTH_TO_COLOUR), WC, HC)
    both = (wrong > 0) & smooth
    assert np.abs(wrong - expected)[both].max() > 0.003


def test_identity_extrinsic_and_equal_intrinsics_give_back_the_depth(scene):
    depth = scene[0].astype(np.float32)
    depth[100:110, 50:200] = 0  # holes stay holes
    out = register_depth(depth, K_DEPTH, K_DEPTH, np.eye(4), WD, HD)
    assert out.dtype == np.float32 and np.array_equal(out, depth)


def test_unregistered_bag_without_extrinsics_is_a_one_line_error(scene, tmp_path):
    depth, _, rgb = scene
    _write_realsense_bag(tmp_path / "rs.bag", depth, rgb, tf=None, frames=1)
    with pytest.raises(ArgenError, match="no extrinsics between them") as exc:
        open_any(tmp_path / "rs.bag")
    assert "\n" not in str(exc.value)
