"""A ROS 1 bag of RGB-D frames (a RealSense Viewer recording, or a ROS RealSense driver's), read with ``rosbags``.

What is taken from the bag (any topic names; RealSense Viewer's ``/device_0/sensor_N/<Stream>/image/data`` and the
ROS driver's ``/camera/...`` topics both fit):

- depth: the ``sensor_msgs/Image`` topic with 16-bit encoding (``16UC1`` / ``mono16``); when there are several,
  the one whose topic says ``aligned`` (depth registered to the colour camera);
- colour: the ``sensor_msgs/Image`` topic with ``rgb8`` / ``bgr8`` / ``rgba8`` / ``bgra8`` / ``mono8`` encoding;
- intrinsics: the ``sensor_msgs/CameraInfo`` topic that shares the longest topic prefix with the colour images
  (``K``; non-zero distortion is refused, as in camera.json), or ``--camera``;
- depth units: a ``std_msgs/Float32`` topic named ``.../Depth Units...`` (metres per unit, RealSense Viewer
  writes it), else 1 mm per unit (RealSense's default), or ``--depth-scale``.

The depth must be registered to the colour image (same size, same intrinsics, or an ``aligned`` topic):
RealSense Viewer records the sensors' raw streams, so record with depth aligned to colour (the ROS driver's
``align_depth``) or align first; an unregistered bag gets a one-line error. Each depth image is paired with the
colour image nearest in time (bag receive time, at most ``MAX_DT`` apart). Reading a frame seeks to its two
messages through the bag's index, so nothing but the index is held in memory.
"""

from __future__ import annotations

import os
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


@dataclass
class BagRecording(RecordingBase):
    """An opened bag (RecordingBase; K from camera_info or --camera; depth_scale: mm per depth unit).

    depth_topic, colour_topic: the streams used; depth_ns, colour_ns: (F,) bag times (ns) of each frame's two
    messages; timestamps: (F,) float64 seconds of the depth images.
    """

    depth_topic: str = ""
    colour_topic: str = ""
    depth_ns: list[int] = field(default_factory=list)
    colour_ns: list[int] = field(default_factory=list)
    timestamps: np.ndarray | None = None
    camera_source: str = "camera_info"  # where K came from: "camera_info" or "--camera"

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
        return self.checked(i, rgb, depth.astype(np.float32) * np.float32(self.depth_scale / bop.MM_PER_M))


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
        K = np.array(_field(ci, "K"), np.float64).reshape(3, 3)
        if any(float(v) != 0.0 for v in _field(ci, "D")):
            raise ArgenError(f"{path}: the colour camera_info gives distortion coefficients: argen renders a pinhole "
                             "camera; undistort the images first")
        if not K[0, 0] > 0:
            raise ArgenError(f"{path}: the colour camera_info has no intrinsics (K is zero); pass --camera")
    else:
        raise ArgenError(f"{path}: no camera_info in the bag; pass --camera camera.json")
    registered = "aligned" in depth_topic.lower() or (
        (int(d0.width), int(d0.height)) == (w, h)
        and (di is None or ci is None or np.allclose(_field(di, "K"), _field(ci, "K"), atol=1e-6)))
    if not registered:
        raise ArgenError(f"{path}: the depth ({depth_topic}, {d0.width}x{d0.height}) is not registered to the colour "
                         f"({colour_topic}, {w}x{h}): record with depth aligned to colour (an 'aligned' topic)")
    if depth_scale is None:
        units = [c for c in reader.connections if c.msgtype == FLOAT32 and "depth units" in c.topic.lower()]
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
                       np.array([t_d[i] / 1e9 for i, _ in pairs]), "camera_info" if camera is None else "--camera")
    rec.read(0)
    return rec


def _field(msg, name: str):
    """A CameraInfo field by its ROS 1 name (K, D) or ROS 2 name (k, d)."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.lower())
