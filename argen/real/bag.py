"""A ROS 1 bag of RGB-D frames (a RealSense Viewer recording, or a ROS RealSense driver's), read with ``rosbags``.

What is taken from the bag (any topic names; RealSense Viewer's ``/device_0/sensor_N/<Stream>/image/data`` and the
ROS driver's ``/camera/...`` topics both fit):

- depth: the ``sensor_msgs/Image`` topic with 16-bit encoding (``16UC1`` / ``mono16``); when there are several,
  the one whose topic says ``aligned`` (depth registered to the colour camera);
- colour: the ``sensor_msgs/Image`` topic with ``rgb8`` / ``bgr8`` / ``rgba8`` / ``bgra8`` / ``mono8`` encoding;
- intrinsics: the ``sensor_msgs/CameraInfo`` topic that shares the longest topic prefix with the colour images
  (``K``; non-zero distortion is refused, as in camera.json), or ``--camera``;
- depth units: a ``std_msgs/Float32`` topic named ``.../Depth Units...`` or ``.../Depth_Units...`` (metres per
  unit, RealSense Viewer writes it), else 1 mm per unit (RealSense's default), or ``--depth-scale``.

Depth that is not registered to the colour image (RealSense Viewer records the sensors' raw streams: another
size, its own intrinsics, a few centimetres beside the colour camera) is registered here, frame by frame
(``register_depth``), from the depth stream's own ``camera_info`` and the two streams' extrinsics, which the
RealSense format stores as ``geometry_msgs/Transform`` messages on ``<stream prefix>/tf/<reference id>``. Only a
bag with neither an ``aligned`` topic, matching intrinsics nor those extrinsics gets a one-line error. Each depth
image is paired with the colour image nearest in time (bag receive time, at most ``MAX_DT`` apart). Reading a frame
seeks to its two messages through the bag's index, so nothing but the index is held in memory.

The RealSense bag format, as librealsense writes and plays it back (IntelRealSense/librealsense at cacc8e701):

- extrinsics: ``ros_file_format.h:362-365`` names the topic ``/device_D/sensor_S/<Type>_<index>/tf/<ref>``;
  ``ros_writer.cpp:122-135`` writes there, once per stream, ``dev.get_extrinsics(stream)``, which
  ``device.cpp:165-178`` computes as ``try_fetch_extrinsics(*pin_stream, stream)``: the transform FROM the
  extrinsics group's reference ("pin": the first stream registered in group ``ref``; depth on D400,
  ``d400-device.cpp:612`` before ``d400-color.cpp:60``) TO the stream, i.e. ``p_stream = R p_reference + t``
  (rs2_extrinsics, column-major rotation, metres: ``rs_sensor.h:103-107``, applied as in ``rs.cpp:4211``). So the
  depth stream's transform is the identity and the colour stream's is depth -> colour. Playback agrees:
  ``playback_device.cpp:174-177`` builds stream1 -> stream2 as ``E2 * inverse(E1)`` (``pose.h:25``: ``a * b``
  applies ``b`` first), which is reference -> stream composition, although its comment at line 176 words it the
  other way round; we follow the code. The quaternion is that of the rotation matrix (``ros_file_format.h:158-205``
  convert it both ways; ``rot2quat`` negates the whole quaternion, the same rotation).
- intrinsics: ``ros_file_format.h:299-302`` and ``ros_writer.cpp:343-365``: ``<stream prefix>/info/camera_info``,
  a ``sensor_msgs/CameraInfo`` with ``K = [fx, 0, ppx, 0, fy, ppy, 0, 0, 1]``, ``D`` = the five rs2 coefficients.
- depth units: ``ros_writer.cpp:480-482`` writes each option as ``std_msgs/Float32`` on
  ``/device_D/sensor_S/option/<name>/value`` with the name's spaces made underscores (``ros_file_format.h:315-319``:
  ``Depth_Units``); ``ros_reader.cpp:1530-1536`` also accepts the spaced name of older files.
- Z16 depth is written with the ``mono16`` encoding (``ros_file_format.h:59``).
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from argen import bop
from argen.errors import ArgenError
from argen.real.recording import RecordingBase, associate

MAX_DT = 0.02  # seconds between a depth image and its colour image
DEPTH_ENCODINGS = ("16uc1", "mono16")
COLOUR_ENCODINGS = {"rgb8": (3, None), "bgr8": (3, [2, 1, 0]), "rgba8": (4, None), "bgra8": (4, [2, 1, 0]),
                    "mono8": (1, None)}
IMAGE, INFO, FLOAT32 = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", "std_msgs/msg/Float32"
TRANSFORM = "geometry_msgs/msg/Transform"
TF_TOPIC = re.compile(r"(?P<stream>.+)/tf/(?P<ref>\d+)")  # <stream prefix>/tf/<reference id> (RealSense format)
GROW_PX = 0.25  # register_depth: how far a depth pixel's footprint is grown on the colour image (pixels)
MAX_FOOTPRINT_PX = 32  # register_depth: a footprint wider than this is a point grazing the colour camera: dropped
_READERS: dict = {}


def _reader(path: Path):
    """This process's open AnyReader of ``path`` (opened on first use; workers open their own)."""
    from rosbags.highlevel import AnyReader  # lazy: only bag recordings need rosbags

    key = (os.getpid(), str(path))
    if key not in _READERS:
        reader = AnyReader([path])
        try:
            reader.open()
        except Exception as exc:  # rosbags raises its own types for corrupt or non-ROS1 files
            raise ArgenError(f"cannot read ROS bag {path}: {exc}") from None
        _READERS[key] = reader
    return _READERS[key]


def image_array(msg, path: Path) -> np.ndarray:
    """A sensor_msgs/Image as (H, W) uint16 (16-bit encodings) or (H, W, 3) uint8 RGB; one-line error otherwise."""
    enc = str(msg.encoding).lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, np.uint8)
    if enc in DEPTH_ENCODINGS:
        img = data.view(">u2" if msg.is_bigendian else "<u2").reshape(h, step // 2)[:, :w]
        return img.astype(np.uint16)
    if enc in COLOUR_ENCODINGS:
        ch, order = COLOUR_ENCODINGS[enc]
        img = data.reshape(h, step)[:, :w * ch].reshape(h, w, ch)
        img = np.repeat(img, 3, axis=2) if ch == 1 else img[..., :3]
        return np.ascontiguousarray(img[..., order] if order else img)
    raise ArgenError(f"{path}: image encoding '{msg.encoding}' is not supported (depth must be 16-bit: 16UC1 or "
                     f"mono16; colour rgb8, bgr8, rgba8, bgra8 or mono8)")


def register_depth(depth: np.ndarray, K_depth: np.ndarray, K_colour: np.ndarray, depth_to_colour: np.ndarray,
                   width: int, height: int) -> np.ndarray:
    """Depth (H_d, W_d) metres (0 = none) seen by the depth camera, as the colour camera (``width`` x ``height``,
    ``K_colour``) sees it: (height, width) float32 metres, 0 where no depth pixel lands.

    As librealsense's ``rs2::align`` to colour (``src/proc/align.cpp:44-90``, ``align_z_to_other`` at 95-120): each
    valid depth pixel is back-projected with ``K_depth`` at its depth, moved by ``depth_to_colour`` ((4, 4), metres,
    p_colour = R p_depth + t) and projected with ``K_colour``; that is done for its top-left and bottom-right corners,
    and the colour pixels in between get its depth, the nearest depth winning where several land. Two deliberate
    differences: the value written is the point's depth in the colour camera (librealsense writes the depth
    camera's z, off by the extrinsic's z translation and rotation, about a millimetre on a D400), and the colour
    pixels filled are those whose centres lie inside the footprint grown by ``GROW_PX``, where librealsense rounds
    both corners to the nearest pixel: that grows it by half a pixel on each side, so with equal intrinsics and no
    motion every depth pixel fills a 2 x 2 block and near objects gain a pixel to the right and below. Growing by a
    quarter pixel still closes the sub-pixel gaps that parallax opens on slanted surfaces, and equal intrinsics
    with an identity extrinsic give back the input exactly. Pinhole only (distortion is refused upstream).
    """
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    R, t = depth_to_colour[:3, :3], depth_to_colour[:3, 3]
    fx, fy, cx, cy = K_depth[0, 0], K_depth[1, 1], K_depth[0, 2], K_depth[1, 2]

    def in_colour(offset: float) -> np.ndarray:
        """(N, 3) the depth pixels' points (pixel + offset, both axes) in the colour camera's frame."""
        p = np.stack([(u + offset - cx) / fx * z, (v + offset - cy) / fy * z, z], axis=1)
        return p @ R.T + t

    centre, corners = in_colour(0.0), [in_colour(-0.5), in_colour(0.5)]
    ok = (centre[:, 2] > 0) & (corners[0][:, 2] > 0) & (corners[1][:, 2] > 0)
    pix = []
    for p in corners:
        uvw = p @ np.asarray(K_colour, np.float64).T
        with np.errstate(divide="ignore", invalid="ignore"):
            pix.append(uvw[:, :2] / uvw[:, 2:])
    lo, hi = np.minimum(*pix) - GROW_PX, np.maximum(*pix) + GROW_PX
    ok &= np.isfinite(lo).all(axis=1) & np.isfinite(hi).all(axis=1) & ((hi - lo) <= MAX_FOOTPRINT_PX).all(axis=1)
    size = np.array([width, height])
    first = np.clip(np.ceil(lo[ok]), 0, size).astype(np.int64)  # the colour pixels with lo <= centre < hi
    last = np.clip(np.ceil(hi[ok]) - 1, -1, size - 1).astype(np.int64)
    count = last - first + 1
    zc = centre[ok, 2]
    out = np.full(width * height, np.inf)
    for dy in range(int(count[:, 1].max(initial=0))):
        for dx in range(int(count[:, 0].max(initial=0))):
            m = (count[:, 0] > dx) & (count[:, 1] > dy)
            np.minimum.at(out, (first[m, 1] + dy) * width + first[m, 0] + dx, zc[m])
    out[np.isinf(out)] = 0.0
    return out.reshape(height, width).astype(np.float32)


@dataclass
class Registration:
    """How a bag's depth stream is registered to its colour camera: K_depth (3, 3) pixels, depth_size (W, H),
    depth_to_colour (4, 4) metres (p_colour = R p_depth + t)."""

    K_depth: np.ndarray
    depth_size: tuple[int, int]
    depth_to_colour: np.ndarray


@dataclass
class BagRecording(RecordingBase):
    """An opened bag (RecordingBase; K from camera_info or --camera; depth_scale: mm per depth unit).

    depth_topic, colour_topic: the streams used; depth_ns, colour_ns: (F,) bag times (ns) of each frame's two
    messages; timestamps: (F,) float64 seconds of the depth images; registration: how the depth is registered to
    the colour camera when the bag holds it unregistered (None: it is registered already).
    """

    depth_topic: str = ""
    colour_topic: str = ""
    depth_ns: list[int] = field(default_factory=list)
    colour_ns: list[int] = field(default_factory=list)
    timestamps: np.ndarray | None = None
    camera_source: str = "camera_info"  # where K came from: "camera_info" or "--camera"
    registration: Registration | None = None

    def _message(self, topic: str, ns: int):
        reader = _reader(self.root)
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _, raw in reader.messages(connections=conns, start=ns, stop=ns + 1):
            return reader.deserialize(raw, conn.msgtype)
        raise ArgenError(f"{self.root}: no message on {topic} at {ns} ns")

    def read(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``i``: rgb (H, W, 3) uint8 and depth (H, W) float32 metres (0 = no measurement)."""
        depth = image_array(self._message(self.depth_topic, self.depth_ns[i]), self.root)
        rgb = image_array(self._message(self.colour_topic, self.colour_ns[i]), self.root)
        if depth.dtype != np.uint16:
            raise ArgenError(f"{self.root}: depth on {self.depth_topic} is not 16-bit")
        metres = depth.astype(np.float32) * np.float32(self.depth_scale / bop.MM_PER_M)
        reg = self.registration
        if reg is not None:
            if (depth.shape[1], depth.shape[0]) != reg.depth_size:
                raise ArgenError(f"depth frame {self.names[i]} of {self.root} is {depth.shape[1]}x{depth.shape[0]}, "
                                 f"its camera_info says {reg.depth_size[0]}x{reg.depth_size[1]}")
            metres = register_depth(metres, reg.K_depth, self.K, reg.depth_to_colour, self.width, self.height)
        return self.checked(i, rgb, metres)


def _transform_matrix(msg) -> np.ndarray:
    """A geometry_msgs/Transform as a (4, 4) matrix (unit quaternion x, y, z, w; translation in metres)."""
    q = np.array([msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w], np.float64)
    x, y, z, w = q / np.linalg.norm(q)
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = [msg.translation.x, msg.translation.y, msg.translation.z]
    return T


def _depth_to_colour(reader, path: Path, depth_topic: str, colour_topic: str) -> np.ndarray | None:
    """The (4, 4) depth -> colour transform from the RealSense ``<stream prefix>/tf/<ref>`` topics (see the module
    docstring: each holds reference -> stream), or None when the bag has none for either stream."""
    streams: dict[str, tuple[str, np.ndarray]] = {}
    for conn in reader.connections:
        match = TF_TOPIC.fullmatch(conn.topic)
        if conn.msgtype == TRANSFORM and match and match["stream"] not in streams:
            for _, _, raw in reader.messages(connections=[conn]):
                streams[match["stream"]] = (match["ref"], _transform_matrix(reader.deserialize(raw, conn.msgtype)))
                break

    def of(topic: str):
        prefixes = [s for s in streams if topic.startswith(s + "/")]
        return streams[max(prefixes, key=len)] if prefixes else None

    depth, colour = of(depth_topic), of(colour_topic)
    if depth is None or colour is None:
        return None
    if depth[0] != colour[0]:
        raise ArgenError(f"{path}: the depth and colour extrinsics have different references (tf/{depth[0]}, "
                         f"tf/{colour[0]}): the bag does not say where one camera is from the other")
    return colour[1] @ np.linalg.inv(depth[1])


def _common_prefix(a: str, b: str) -> int:
    return len(os.path.commonprefix([a, b]))


def open_bag(path: str | Path, depth_scale: float | None = None, camera: bop.CameraFile | None = None) -> BagRecording:
    """Open and check a ROS 1 bag (see the module docstring); depth_scale (mm per unit) and camera override the
    bag's depth units and camera_info."""
    path = Path(path)
    if not path.is_file():
        raise ArgenError(f"ROS bag not found: {path}")
    reader = _reader(path)
    images = [c for c in reader.connections if c.msgtype == IMAGE]
    stamps: dict[str, list[int]] = {}
    first: dict[str, object] = {}
    for conn, ns, raw in reader.messages(connections=images):
        stamps.setdefault(conn.topic, []).append(ns)
        if conn.topic not in first:
            first[conn.topic] = reader.deserialize(raw, conn.msgtype)
    enc = {t: str(m.encoding).lower() for t, m in first.items()}
    depth_topics = [t for t, e in enc.items() if e in DEPTH_ENCODINGS]
    colour_topics = [t for t, e in enc.items() if e in COLOUR_ENCODINGS]
    if not depth_topics:
        other = [f"{t} ({first[t].encoding})" for t in enc if "depth" in t.lower()]
        raise ArgenError(f"{path}: no 16-bit depth images (16UC1 or mono16)"
                         + (f"; found {', '.join(other)}: depth must be 16-bit" if other else "; no frames"))
    if not colour_topics:
        raise ArgenError(f"{path}: no colour images (rgb8, bgr8, rgba8, bgra8 or mono8)")
    depth_topic = sorted(depth_topics, key=lambda t: ("aligned" not in t.lower(), t))[0]
    colour_topic = sorted(colour_topics)[0]
    d0, c0 = first[depth_topic], first[colour_topic]
    w, h = int(c0.width), int(c0.height)
    infos = {}
    for conn, _, raw in reader.messages(connections=[c for c in reader.connections if c.msgtype == INFO]):
        infos.setdefault(conn.topic, reader.deserialize(raw, conn.msgtype))

    def info_for(topic: str):
        if not infos:
            return None
        return infos[max(sorted(infos), key=lambda t: _common_prefix(t, topic))]

    ci, di = info_for(colour_topic), info_for(depth_topic)
    if camera is not None:
        K = camera.K
        if (camera.width, camera.height) not in ((None, None), (w, h)):
            raise ArgenError(f"--camera says {camera.width}x{camera.height} but the colour images of {path} are {w}x{h}")
    elif ci is not None:
        K = _pinhole_K(ci, f"{path}: the colour camera_info", "argen renders a pinhole camera; undistort the images "
                       "first", "pass --camera")
    else:
        raise ArgenError(f"{path}: no camera_info in the bag; pass --camera camera.json")
    aligned = "aligned" in depth_topic.lower()
    same_grid = (int(d0.width), int(d0.height)) == (w, h) and (
        di is None or ci is None or np.allclose(_field(di, "K"), _field(ci, "K"), atol=1e-6))
    extrinsics = None if aligned else _depth_to_colour(reader, path, depth_topic, colour_topic)
    registration = None
    if extrinsics is not None and not (same_grid and np.allclose(extrinsics, np.eye(4), atol=1e-9)):
        registration = _registration(path, depth_topic, d0, di, extrinsics)
    elif not (aligned or same_grid):
        raise ArgenError(f"{path}: the depth ({depth_topic}, {d0.width}x{d0.height}) is not registered to the colour "
                         f"({colour_topic}, {w}x{h}) and the bag holds no extrinsics between them (RealSense's "
                         f".../tf/N topics): record with depth aligned to colour (an 'aligned' topic)")
    if depth_scale is None:
        units = [c for c in reader.connections
                 if c.msgtype == FLOAT32 and "depth units" in c.topic.lower().replace("_", " ")]
        depth_scale = 1.0
        for conn, _, raw in reader.messages(connections=units):
            depth_scale = float(reader.deserialize(raw, conn.msgtype).data) * bop.MM_PER_M
            break
    if not depth_scale > 0:
        raise ArgenError(f"depth_scale must be positive (mm per depth unit), got {depth_scale:g}")
    t_d = np.array(stamps[depth_topic], np.int64)
    t_c = np.array(stamps[colour_topic], np.int64)
    pairs = associate(t_d / 1e9, t_c / 1e9, MAX_DT)
    if not pairs:
        raise ArgenError(f"{path}: no depth image within {MAX_DT:g} s of a colour image: no frames")
    rec = BagRecording(path, K, float(depth_scale), w, h, [f"{k:06d}" for k in range(len(pairs))], depth_topic,
                       colour_topic, [int(t_d[i]) for i, _ in pairs], [int(t_c[j]) for _, j in pairs],
                       np.array([t_d[i] / 1e9 for i, _ in pairs]), "camera_info" if camera is None else "--camera",
                       registration)
    rec.read(0)
    return rec


def _registration(path: Path, depth_topic: str, d0, di, extrinsics: np.ndarray) -> Registration:
    """The Registration of an unregistered depth stream: its camera_info's K (pinhole) and the extrinsics."""
    if di is None:
        raise ArgenError(f"{path}: no camera_info for the depth ({depth_topic}) to register it to the colour camera")
    K_depth = _pinhole_K(di, f"{path}: the depth camera_info", "argen registers depth with a pinhole model; "
                         "undistort the depth first", "cannot register the depth")
    return Registration(K_depth, (int(d0.width), int(d0.height)), extrinsics)


def _pinhole_K(info, what: str, if_distorted: str, if_zero: str) -> np.ndarray:
    """A CameraInfo's K (3, 3), refused (one-line error: ``what`` + reason + remedy) if distorted or zero."""
    K = np.array(_field(info, "K"), np.float64).reshape(3, 3)
    if any(float(v) != 0.0 for v in _field(info, "D")):
        raise ArgenError(f"{what} gives distortion coefficients: {if_distorted}")
    if not K[0, 0] > 0:
        raise ArgenError(f"{what} has no intrinsics (K is zero); {if_zero}")
    return K


def _field(msg, name: str):
    """A CameraInfo field by its ROS 1 name (K, D) or ROS 2 name (k, d)."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.lower())
