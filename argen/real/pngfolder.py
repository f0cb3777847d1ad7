"""A plain folder of colour and 16-bit depth images with a BOP ``camera.json``, as ``argen capture`` reads it.

Layout of DIR::

    camera.json            BOP camera.json: fx, fy, cx, cy (pixels), depth_scale (mm per depth-PNG unit)
    NAME_color.png, ...    colour (8-bit PNG, or JPEG) and depth (16-bit single-channel PNG) side by side

A PNG is depth when its header says 16-bit greyscale, colour otherwise. A colour and a depth image are one
frame when their names agree once the words rgb / color / colour / depth and the separators around them are
taken out (``000001_color.png`` + ``000001_depth.png``, ``rgb_0001.png`` + ``depth_0001.png``,
``0001.jpg`` + ``0001.png``). Frames are taken in that name's sorted order.
"""

from __future__ import annotations

import re
from pathlib import Path

from argen import bop
from argen.errors import ArgenError
from argen.real.recording import RGB_EXTS, Recording, intrinsics_of, png_recording

_WORDS = re.compile(r"(?i)[_\-. ]*(rgb|colou?r|depth)[_\-. ]*")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_is_depth(path: Path) -> bool:
    """Whether ``path`` is a 16-bit greyscale PNG (read from its IHDR header: bit depth 16, colour type 0)."""
    with open(path, "rb") as f:
        head = f.read(26)
    return len(head) == 26 and head[:8] == PNG_SIGNATURE and head[24] == 16 and head[25] == 0


def frame_key(path: Path) -> str:
    """The name a colour and a depth image of one frame share: the stem without rgb/colour/depth words."""
    return _WORDS.sub("_", path.stem).strip("_") or path.stem


def is_png_folder(root: Path) -> bool:
    """Whether folder ``root`` holds images directly (the plain layout), not in rgb/ and depth/ subfolders."""
    return any(p.suffix.lower() in RGB_EXTS and p.is_file() for p in root.iterdir())


def open_png_folder(root: str | Path, depth_scale: float | None = None,
                    camera: bop.CameraFile | None = None) -> Recording:
    """Open and check a plain folder of colour and depth images (see the module docstring)."""
    root = Path(root)
    cam, depth_scale, source = intrinsics_of(root, camera, depth_scale)
    colour: dict[str, Path] = {}
    depth: dict[str, Path] = {}
    for p in sorted(root.iterdir()):
        if p.suffix.lower() not in RGB_EXTS or not p.is_file():
            continue
        side = depth if p.suffix.lower() == ".png" and png_is_depth(p) else colour
        if side is colour and "depth" in p.stem.lower():
            raise ArgenError(f"{p} is named a depth image but is not a 16-bit greyscale PNG: depth must be 16-bit")
        key = frame_key(p)
        if key in side:
            raise ArgenError(f"{root}: {side[key].name} and {p.name} are both the {'depth' if side is depth else 'colour'}"
                             f" image of frame '{key}'")
        side[key] = p
    if set(colour) != set(depth):
        odd = sorted(set(colour) ^ set(depth))
        raise ArgenError(f"recording {root}: {len(colour)} colour and {len(depth)} 16-bit depth images do not pair up "
                         f"by name (e.g. frame '{odd[0]}' has no partner; is its depth image 16-bit?)")
    names = sorted(colour)
    return png_recording(root, cam, depth_scale, names, [colour[n] for n in names], [depth[n] for n in names], None,
                         "colour and 16-bit depth PNGs", source)
