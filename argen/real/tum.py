"""A recording in the TUM RGB-D benchmark's layout (Sturm et al., IROS 2012), as ``argen capture`` reads it.

Layout of DIR::

    rgb.txt, depth.txt   association lists: "TIMESTAMP FILENAME" per line (seconds; "#" lines are comments),
                         FILENAME relative to DIR (rgb/NAME.png, depth/NAME.png)
    depth/*.png          16-bit depth, value / 5000 = metres (0 = no measurement), registered to the colour
    rgb/*.png            8-bit colour
    camera.json          optional BOP camera.json (intrinsics; its depth_scale is not used: TUM's depth is 1/5000 m,
                         change it with --depth-scale)

Each depth image is paired with the colour image nearest in time, at most ``MAX_DT`` apart (the benchmark's
associate.py does the same); unpaired images are left out. Intrinsics: ``--camera``, else DIR/camera.json,
else the benchmark's default for registered depth (:data:`TUM_DEFAULT`, fx = fy = 525, cx = 319.5, cy = 239.5).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from argen import bop
from argen.errors import ArgenError
from argen.real.recording import Recording, associate, intrinsics_of, png_recording

DEPTH_SCALE = 0.2  # mm per depth-PNG unit: TUM stores 5000 units per metre
MAX_DT = 0.02  # seconds between a depth image and its colour image
#: The TUM RGB-D benchmark's default intrinsics (the ROS default of the Kinect, for registered depth), 640x480.
TUM_DEFAULT = bop.CameraFile(np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]]), None, 640, 480, [])


def is_tum(root: Path) -> bool:
    """Whether folder ``root`` is in the TUM layout (it has both association lists)."""
    return (root / "rgb.txt").is_file() and (root / "depth.txt").is_file()


def read_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """A TUM association list: (timestamps (N,) seconds, file names (N,)); one-line errors for bad lines."""
    stamps, files = [], []
    for k, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        try:
            if len(parts) != 2:
                raise ValueError(f"{len(parts)} fields")
            stamps.append(float(parts[0]))
        except ValueError as exc:
            raise ArgenError(f"{path}:{k}: lines must be 'TIMESTAMP FILENAME' ({exc})") from None
        files.append(parts[1])
    return np.array(stamps, np.float64), files


def open_tum(root: str | Path, depth_scale: float | None = None, camera: bop.CameraFile | None = None) -> Recording:
    """Open and check a TUM RGB-D folder (see the module docstring). depth_scale: mm per unit (default TUM's 0.2)."""
    root = Path(root)
    cam, depth_scale, source = intrinsics_of(root, camera, DEPTH_SCALE if depth_scale is None else depth_scale,
                                             default_camera=TUM_DEFAULT)
    t_rgb, f_rgb = read_list(root / "rgb.txt")
    t_depth, f_depth = read_list(root / "depth.txt")
    pairs = associate(t_depth, t_rgb, MAX_DT)
    names = [Path(f_depth[i]).stem for i, _ in pairs]
    if len(set(names)) != len(names):
        names = [f"{t_depth[i]:.6f}" for i, _ in pairs]
    for f in [f_depth[i] for i, _ in pairs[:1]] + [f_rgb[j] for _, j in pairs[:1]]:
        if not (root / f).is_file():
            raise ArgenError(f"{root / f}: listed in the TUM association lists but missing")
    return png_recording(root, cam, depth_scale, names, [root / f_rgb[j] for _, j in pairs],
                         [root / f_depth[i] for i, _ in pairs], np.array([t_depth[i] for i, _ in pairs]),
                         f"no depth image within {MAX_DT:g} s of a colour image in depth.txt and rgb.txt", source)
