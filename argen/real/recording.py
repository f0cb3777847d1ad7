"""A recorded RGB-D sequence from a real sensor, as ``argen capture --recording DIR`` reads it.

Layout of DIR::

    camera.json      {"fx", "fy", "cx", "cy"} or {"cam_K": [9 values]} or {"K": [[3x3]]}, pixels;
                     "depth_scale": BOP convention, millimetres per depth-PNG unit (1.0 for RealSense,
                     Azure Kinect and Kinect v2 raw PNGs); optional "width", "height" (checked).
    rgb/NAME.png     colour frames (.png or .jpg), 8-bit
    depth/NAME.png   16-bit depth PNGs registered to the colour camera (same size, same pixel grid)
    timestamps.txt   optional: one line per frame, "NAME SECONDS" or just "SECONDS" in frame order

Frames pair up by NAME and are taken in sorted NAME order. The images must be undistorted (the
renderer is a pinhole camera): a non-zero "dist" in camera.json is refused.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from argen import bop
from argen.errors import ArgenError

RGB_EXTS = (".png", ".jpg", ".jpeg")
PLAUSIBLE_DEPTH_M = (0.1, 10.0)  # median valid depth of a frame, metres


@dataclass
class RecordingBase:
    """What every opened recording has (argen.real.readers opens them). root: its folder or file; K: (3, 3)
    float64 pixels; depth_scale: mm per depth unit; width, height: pixels; names: frame names in order.

    Subclasses add ``read(i) -> (rgb (H, W, 3) uint8, depth (H, W) float32 metres, 0 = none)``, ``timestamps``
    ((F,) float64 seconds or None) and ``camera_source`` (where K came from)."""

    root: Path
    K: np.ndarray
    depth_scale: float
    width: int
    height: int
    names: list[str]

    def __len__(self) -> int:
        return len(self.names)

    def checked(self, i: int, rgb: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rgb, depth) of frame ``i`` after checking that both have the camera's size (one-line error if not)."""
        for what, img in (("colour", rgb), ("depth", depth)):
            if img.shape[:2] != (self.height, self.width):
                raise ArgenError(f"{what} frame {self.names[i]} of {self.root} is {img.shape[1]}x{img.shape[0]}, the "
                                 f"camera is {self.width}x{self.height}")
        return rgb, depth


@dataclass
class Recording(RecordingBase):
    """An opened recording of image files. rgb_paths, depth_paths: each frame's files; timestamps: (F,) float64
    seconds or None; camera_source: where K came from."""

    rgb_paths: list[Path] = field(default_factory=list)
    depth_paths: list[Path] = field(default_factory=list)
    timestamps: np.ndarray | None = None
    camera_source: str = "camera.json"  # where K came from: a camera.json path, "--camera" or "default"

    def read(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``i``: rgb (H, W, 3) uint8 and depth (H, W) float32 metres (0 = no measurement)."""
        return self.checked(i, bop.read_rgb(self.rgb_paths[i]), read_depth_png(self.depth_paths[i], self.depth_scale))


def read_depth_png(path: Path, depth_scale: float) -> np.ndarray:
    """A 16-bit depth PNG in metres: (H, W) float32, with a check that the values are plausible depths."""

    img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH)
    if img is None:
        raise ArgenError(f"cannot read depth image {path}: missing, corrupt or not an image")
    if img.dtype != np.uint16:
        raise ArgenError(f"depth image {path} is {img.dtype}, not 16-bit: depth must be a 16-bit PNG")
    depth = img.astype(np.float32) * np.float32(depth_scale / bop.MM_PER_M)
    valid = depth[depth > 0]
    if valid.size:
        med = float(np.median(valid))
        lo, hi = PLAUSIBLE_DEPTH_M
        if not lo <= med <= hi:
            raise ArgenError(f"depth image {path} has median depth {med:.4g} m with depth_scale {depth_scale:g} "
                             f"mm per unit: wrong depth units? (set depth_scale in camera.json or --depth-scale)")
    return depth


def _frames(folder: Path, exts: tuple[str, ...]) -> dict[str, Path]:
    if not folder.is_dir():
        raise ArgenError(f"recording folder has no {folder.name}/ subfolder: {folder}")
    return {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() in exts and p.is_file()}


def _timestamps(path: Path, names: list[str]) -> np.ndarray | None:
    if not path.is_file():
        return None
    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    try:
        if rows and all(len(r) == 2 for r in rows):
            by_name = {r[0]: float(r[1]) for r in rows}
            missing = [n for n in names if n not in by_name]
            if missing:
                raise ArgenError(f"{path}: no timestamp for frame {missing[0]} ({len(missing)} frames missing)")
            return np.array([by_name[n] for n in names])
        if rows and all(len(r) == 1 for r in rows):
            if len(rows) != len(names):
                raise ArgenError(f"{path} has {len(rows)} timestamps for {len(names)} frames")
            return np.array([float(r[0]) for r in rows])
    except ValueError as exc:
        raise ArgenError(f"{path}: malformed timestamp ({exc})") from None
    raise ArgenError(f"{path}: lines must be 'NAME SECONDS' or 'SECONDS'")


def intrinsics_of(root: Path, camera: bop.CameraFile | None = None, depth_scale: float | None = None,
                  default_depth_scale: float | None = None,
                  default_camera: bop.CameraFile | None = None) -> tuple[bop.CameraFile, float, str]:
    """The intrinsics and depth scale a PNG recording is read with, and where they came from.

    In order: ``camera`` (``--camera``), ``root/camera.json``, ``default_camera`` (a layout's convention, TUM's).
    The depth scale (mm per depth-PNG unit): ``depth_scale`` (``--depth-scale``), the camera file's, then
    ``default_depth_scale``. Returns (camera, depth_scale, source); one-line errors for what is missing or wrong.
    """
    cam_p = root / bop.CAMERA_FILE
    if camera is not None:
        cam, source = camera, "--camera"
    elif cam_p.is_file():
        cam, source = bop.load_camera(cam_p), str(cam_p)
    elif default_camera is not None:
        cam, source = default_camera, "default"
    else:
        raise ArgenError(f"recording {root} has no camera.json (intrinsics fx, fy, cx, cy and depth_scale); "
                         "add it or pass --camera camera.json")
    if any(v != 0.0 for v in cam.dist):
        raise ArgenError(f"{source} gives distortion coefficients: undistort the frames first (argen renders a "
                         "pinhole camera)")
    if depth_scale is None:
        depth_scale = cam.depth_scale if cam.depth_scale is not None else default_depth_scale
    if depth_scale is None:
        raise ArgenError(f"{source} has no depth_scale (mm per depth-PNG unit, 1.0 for RealSense); "
                         "add it or pass --depth-scale")
    try:
        depth_scale = float(depth_scale)
    except (TypeError, ValueError):
        raise ArgenError(f"depth_scale must be a number, got {depth_scale!r}") from None
    if not depth_scale > 0:
        raise ArgenError(f"depth_scale must be positive (mm per depth-PNG unit), got {depth_scale:g}")
    return cam, depth_scale, source


def png_recording(root: Path, cam: bop.CameraFile, depth_scale: float, names: list[str], rgb_paths: list[Path],
                  depth_paths: list[Path], timestamps: np.ndarray | None, what: str, source: str) -> Recording:
    """A Recording of paired image files, checked: frames present, size as the camera says, depth 16-bit in
    plausible units (first frame). what: how to name the frames in the error for none; source: where the
    camera came from (intrinsics_of)."""
    if not names:
        raise ArgenError(f"recording {root} holds no frames ({what})")
    first = bop.read_rgb(rgb_paths[0])
    h, w = first.shape[:2]
    if (cam.width is not None and cam.width != w) or (cam.height is not None and cam.height != h):
        raise ArgenError(f"the camera says {cam.width}x{cam.height} but the frames of {root} are {w}x{h}")
    rec = Recording(root, cam.K, depth_scale, w, h, names, rgb_paths, depth_paths, timestamps, source)
    rec.read(0)  # size and depth-unit checks on the first frame before any work starts
    return rec


def associate(t_a: np.ndarray, t_b: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """Pairs (i, j) of stamps t_a[i], t_b[j] (seconds) at most ``max_dt`` apart, each index used once, closest
    pairs first (the TUM benchmark's association); returned in t_a order."""
    t_a, t_b = np.asarray(t_a, np.float64), np.asarray(t_b, np.float64)
    if not len(t_a) or not len(t_b):
        return []
    dt = np.abs(t_a[:, None] - t_b[None, :])
    cand = np.argwhere(dt <= max_dt)
    cand = cand[np.argsort(dt[cand[:, 0], cand[:, 1]], kind="stable")]
    used_a, used_b, pairs = set(), set(), []
    for i, j in cand:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((int(i), int(j)))
    return sorted(pairs)


def open_recording(root: str | Path, depth_scale: float | None = None,
                   camera: bop.CameraFile | None = None) -> Recording:
    """Open and check a recording folder (see the module docstring); depth_scale overrides camera.json's,
    camera (a BOP camera.json read by bop.load_camera, ``--camera``) its intrinsics."""
    root = Path(root)
    if not root.is_dir():
        raise ArgenError(f"recording folder not found: {root}")
    cam, depth_scale, source = intrinsics_of(root, camera, depth_scale)
    rgb, depth = _frames(root / "rgb", RGB_EXTS), _frames(root / "depth", (".png",))
    if len(rgb) != len(depth) or set(rgb) != set(depth):
        odd = sorted(set(rgb) ^ set(depth))
        raise ArgenError(f"recording {root}: {len(rgb)} colour and {len(depth)} depth frames do not pair up by name "
                         f"(e.g. '{odd[0]}' has no partner)")
    names = sorted(rgb)
    return png_recording(root, cam, depth_scale, names, [rgb[n] for n in names], [depth[n] for n in names],
                         _timestamps(root / "timestamps.txt", names), "rgb/*.png and depth/*.png", source)


def write_recording(root: str | Path, K: np.ndarray, frames: list[tuple[np.ndarray, np.ndarray]],
                    depth_scale: float = 1.0, timestamps: np.ndarray | None = None) -> None:
    """Write frames [(rgb (H, W, 3) uint8, depth (H, W) metres)] as a recording folder (names 000000...)."""
    root = Path(root)
    h, w = frames[0][1].shape
    bop.save_camera(root / bop.CAMERA_FILE, K, w, h, depth_scale)
    for i, (rgb, depth) in enumerate(frames):
        bop.write_png(root / "rgb" / f"{i:06d}.png", rgb)
        bop.write_depth(root / "depth" / f"{i:06d}.png", depth, depth_scale)
    if timestamps is not None:
        (root / "timestamps.txt").write_text("".join(f"{i:06d} {t:.6f}\n" for i, t in enumerate(timestamps)))
