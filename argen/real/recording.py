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

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from argen import bop
from argen.errors import ArgenError

RGB_EXTS = (".png", ".jpg", ".jpeg")
PLAUSIBLE_DEPTH_M = (0.1, 10.0)  # median valid depth of a frame, metres


@dataclass
class Recording:
    """An opened recording. K: (3, 3) float64 pixels; depth_scale: mm per PNG unit; width, height: pixels.

    names: frame names in order; rgb_paths, depth_paths: their files; timestamps: (F,) float64 seconds
    or None.
    """

    root: Path
    K: np.ndarray
    depth_scale: float
    width: int
    height: int
    names: list[str]
    rgb_paths: list[Path]
    depth_paths: list[Path]
    timestamps: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.names)

    def read(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``i``: rgb (H, W, 3) uint8 and depth (H, W) float32 metres (0 = no measurement)."""
        rgb = bop.read_rgb(self.rgb_paths[i])
        depth = read_depth_png(self.depth_paths[i], self.depth_scale)
        for what, img in (("colour", rgb), ("depth", depth)):
            if img.shape[:2] != (self.height, self.width):
                raise ArgenError(f"{what} frame {self.names[i]} is {img.shape[1]}x{img.shape[0]}, camera.json "
                                 f"says {self.width}x{self.height}")
        return rgb, depth


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


def open_recording(root: str | Path, depth_scale: float | None = None) -> Recording:
    """Open and check a recording folder (see the module docstring); depth_scale overrides camera.json's."""
    root = Path(root)
    if not root.is_dir():
        raise ArgenError(f"recording folder not found: {root}")
    cam_p = root / bop.CAMERA_FILE
    if not cam_p.is_file():
        raise ArgenError(f"recording {root} has no camera.json (intrinsics fx, fy, cx, cy and depth_scale)")
    cam = bop.load_camera(cam_p)
    K = cam.K
    if any(v != 0.0 for v in cam.dist):
        raise ArgenError(f"{cam_p} gives distortion coefficients: undistort the frames first (argen renders a pinhole camera)")
    if depth_scale is None:
        if cam.depth_scale is None:
            raise ArgenError(f"{cam_p} has no depth_scale (mm per depth-PNG unit, 1.0 for RealSense); "
                             "add it or pass --depth-scale")
        depth_scale = cam.depth_scale
    try:
        depth_scale = float(depth_scale)
    except (TypeError, ValueError):
        raise ArgenError(f"depth_scale must be a number, got {depth_scale!r}") from None
    if not depth_scale > 0:
        raise ArgenError(f"depth_scale must be positive (mm per depth-PNG unit), got {depth_scale:g}")
    rgb, depth = _frames(root / "rgb", RGB_EXTS), _frames(root / "depth", (".png",))
    if len(rgb) != len(depth) or set(rgb) != set(depth):
        odd = sorted(set(rgb) ^ set(depth))
        raise ArgenError(f"recording {root}: {len(rgb)} colour and {len(depth)} depth frames do not pair up by name "
                         f"(e.g. '{odd[0]}' has no partner)")
    if not rgb:
        raise ArgenError(f"recording {root} holds no frames (rgb/*.png and depth/*.png)")
    names = sorted(rgb)
    first = bop.read_rgb(rgb[names[0]])
    h, w = first.shape[:2]
    if (cam.width is not None and cam.width != w) or (cam.height is not None and cam.height != h):
        raise ArgenError(f"{cam_p} says {cam.width}x{cam.height} but the frames are {w}x{h}")
    rec = Recording(root, K, depth_scale, w, h, names, [rgb[n] for n in names], [depth[n] for n in names],
                    _timestamps(root / "timestamps.txt", names))
    rec.read(0)  # size and depth-unit checks on the first frame before any work starts
    return rec


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
