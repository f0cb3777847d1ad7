"""Which reader opens a recording: ``argen capture --recording PATH`` takes any of these as they are.

- a ``.bag`` file: a ROS 1 bag (RealSense), argen.real.bag;
- a folder with ``rgb.txt`` and ``depth.txt``: the TUM RGB-D layout, argen.real.tum;
- a folder with ``rgb/`` and ``depth/``: argen's own layout (camera.json), argen.real.recording;
- a folder of colour and 16-bit depth images with a BOP ``camera.json``: argen.real.pngfolder.

``--camera`` is a BOP camera.json, or ``tum`` for the TUM benchmark's default intrinsics.
"""

from __future__ import annotations

from pathlib import Path

from argen import bop
from argen.errors import ArgenError
from argen.real.bag import open_bag
from argen.real.pngfolder import is_png_folder, open_png_folder
from argen.real.recording import RecordingBase, open_recording
from argen.real.tum import TUM_DEFAULT, is_tum, open_tum

CAMERA_NAMES = {"tum": TUM_DEFAULT}
LAYOUTS = ("bag", "tum", "folders", "plain")


def camera_arg(value: str | Path | None) -> bop.CameraFile | None:
    """``--camera``: a named camera (``tum``) or a BOP camera.json path; None stays None."""
    if value is None:
        return None
    if str(value).lower() in CAMERA_NAMES:
        return CAMERA_NAMES[str(value).lower()]
    if not Path(value).is_file():
        raise ArgenError(f"--camera {value}: no such camera.json (or one of: {', '.join(CAMERA_NAMES)})")
    return bop.load_camera(value)


def layout_of(path: Path) -> str:
    """The layout of recording ``path``: one of LAYOUTS; one-line error when it is none of them."""
    if path.is_file() and path.suffix.lower() == ".bag":
        return "bag"
    if not path.exists():
        raise ArgenError(f"recording not found: {path}")
    if not path.is_dir():
        raise ArgenError(f"recording {path} is neither a folder nor a .bag file")
    if is_tum(path):
        return "tum"
    if (path / "rgb").is_dir() or (path / "depth").is_dir():
        return "folders"
    if is_png_folder(path):
        return "plain"
    raise ArgenError(f"recording {path} holds no frames: expected rgb/ and depth/ with camera.json, TUM's rgb.txt "
                     "and depth.txt, colour and 16-bit depth images with camera.json, or a .bag file")


def open_any(path: str | Path, depth_scale: float | None = None,
             camera: bop.CameraFile | None = None) -> RecordingBase:
    """Open recording ``path`` in whichever layout it has. depth_scale: mm per depth unit (``--depth-scale``);
    camera: intrinsics overriding the recording's (``--camera``)."""
    path = Path(path)
    layout = layout_of(path)
    opener = {"bag": open_bag, "tum": open_tum, "folders": open_recording, "plain": open_png_folder}[layout]
    return opener(path, depth_scale, camera)
