"""Draw a labelled frame for checking labels by eye (``argen preview``).

The image: the frame's RGB (from the source BOP dataset when it is still there, else the labelled
points' own colours splatted at their pixels), the object points tinted with their instance's colour,
and each instance's 3D box drawn from its 9 control points (12 edges and the centre) with cam_K.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from argen import bop
from argen.errors import ArgenError
from argen.features import BOX_EDGES, palette, project
from argen.h5 import FrameLabels, LabelFile
from argen.label import (
    LabelConfig,
    Labeller,
    dataset_frames,
    dataset_pixel_centres,
    default_max_depth,
    load_label_objects,
    resolve_models,
)


def splat(frame: FrameLabels) -> np.ndarray:
    """(H,W,3) uint8 image of the points' colours at their pixels (3x3 dots), black elsewhere."""
    h, w = (int(v) for v in frame.image_size)
    img = np.zeros((h, w, 3), np.uint8)
    img[frame.pixel[:, 0], frame.pixel[:, 1]] = np.clip(frame.features[:, 3:6] * 255 + 0.5, 0, 255).astype(np.uint8)
    return cv2.dilate(img, np.ones((3, 3), np.uint8))


def draw_frame(frame: FrameLabels, rgb: np.ndarray | None = None, alpha: float = 0.6) -> np.ndarray:
    """The preview of one frame. rgb: (H,W,3) uint8 background or None (splatted points). Returns (H,W,3) uint8."""
    img = (rgb if rgb is not None else splat(frame)).copy()
    m = len(frame.instances)
    cols = palette(max(m, 1))
    fg = frame.instance >= 0
    r, c = frame.pixel[fg, 0], frame.pixel[fg, 1]
    mask = np.zeros(img.shape[:2], np.int32) - 1
    mask[r, c] = frame.instance[fg]
    mask = cv2.dilate((mask + 1).astype(np.uint16), np.ones((3, 3), np.uint8)).astype(np.int32) - 1
    rr, cc = np.nonzero(mask >= 0)
    img[rr, cc] = (img[rr, cc] * (1 - alpha) + cols[mask[rr, cc]] * alpha).astype(np.uint8)
    K = frame.cam_K.astype(np.float64)
    for k in range(m):
        cps = frame.instances.control_points[k]
        if np.any(cps[:, 2] <= 0.01):
            continue
        uv = np.round(project(cps, K) * 16).astype(np.int32)  # 4 fractional bits for cv2 shift
        colour = tuple(int(v) for v in cols[k])
        for a, b in BOX_EDGES:
            cv2.line(img, tuple(uv[a]), tuple(uv[b]), colour, 1, cv2.LINE_AA, shift=4)
        cv2.circle(img, tuple(uv[8]), 3 * 16, colour, -1, cv2.LINE_AA, shift=4)
        txt = f"{frame.instances.obj_id[k]}"
        cv2.putText(img, txt, (int(uv[8][0] / 16) + 5, int(uv[8][1] / 16) - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    colour, 1, cv2.LINE_AA)
    return img


def source_rgb(lf: LabelFile, frame: FrameLabels) -> np.ndarray | None:
    """The frame's RGB from the dataset the file was made from, or None when it is gone or differs in size."""
    root = Path(str(lf.attrs.get("source_dataset", "")))
    split = str(lf.attrs.get("source_split", ""))
    if not root.is_dir() or not split:
        return None
    p = bop.rgb_path(root, split, frame.scene_id, frame.im_id)
    if not p.is_file():
        return None
    rgb = bop.read_rgb(p)
    return rgb if rgb.shape[:2] == tuple(int(v) for v in frame.image_size) else None


def preview_file(path: str | os.PathLike, index: int, out: str | os.PathLike) -> FrameLabels:
    """Write the preview of frame ``index`` of a label file to ``out`` (PNG); returns the frame."""
    with LabelFile(path) as lf:
        if not (0 <= index < lf.num_frames):
            raise ArgenError(f"--frame {index} is out of range: {path} has {lf.num_frames} frames")
        frame = lf.frame(index)
        img = draw_frame(frame, source_rgb(lf, frame))
    bop.write_png(out, img)
    return frame


def preview_bop(dataset: str | os.PathLike, split: str, index: int, out: str | os.PathLike,
                models: str | os.PathLike | None = None, cfg=None) -> FrameLabels:
    """Label frame ``index`` (in split order) of a BOP dataset on the fly and write its preview to ``out``."""

    root = Path(dataset)
    scenes, frames = dataset_frames(root, split)
    if not (0 <= index < len(frames)):
        raise ArgenError(f"--frame {index} is out of range: {root / split} has {len(frames)} frames")
    sid, im = frames[index]
    scene = scenes[sid]
    cfg = cfg or LabelConfig()

    if cfg.max_depth is None:
        cfg = replace(cfg, max_depth=default_max_depth(root))
    if cfg.pixel_centres is None:
        cfg = replace(cfg, pixel_centres=dataset_pixel_centres(root))
    cfg.check()
    ids = sorted({g.obj_id for g in scene.gts[im]})
    objects = load_label_objects(resolve_models(root, Path(models) if models else None), ids)
    frame, _ = Labeller(objects, cfg).label_frame(scene, im)
    bop.write_png(out, draw_frame(frame, scene.read_rgb(im)))
    return frame
