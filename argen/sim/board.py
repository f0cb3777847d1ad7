"""The marker board: a LineMOD-style square ring of ArUco markers around a free central area.

Board frame (= world frame of a capture): origin at the board centre on its top surface, z along
the board normal pointing up (away from the table), x to the right and y up *in the texture image*.
Texture row 0 is y = +side/2 and column 0 is x = -side/2; a texture of W x W pixels covers the whole
board, so texture pixel (u, v) (u column, v row, pixel centres at integers) is the board point

    x = -side/2 + (u + 0.5) / ppm,    y = side/2 - (v + 0.5) / ppm,    z = 0,    ppm = W / side.

Seen from above (from +z) the texture therefore appears upright and unmirrored, which is what
``cv2.aruco`` needs to decode the markers. ``texture_uv`` gives the matching OpenGL texture
coordinates (v up) for a textured quad.

Markers are numbered 0..4(n-1)-1 clockwise as seen from above, starting at the top-left corner of
the ring (top row left to right, right column downwards, bottom row right to left, left column up).
"""

from __future__ import annotations

from functools import cached_property
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from argen.config import BoardConfig
from argen.errors import ArgenError

FREE_AREA_SAFETY = 0.005  # metres kept clear between the free area and the inner edge of the ring
INCH = 0.0254  # metres


def texture_uv(points_xy: np.ndarray, side: float) -> np.ndarray:
    """OpenGL texture coordinates (v up) of board-frame points for the board texture.

    points_xy: (N, 2) board-frame x, y, metres. side: board side, metres.
    Returns (N, 2) float64 (u, v) in [0, 1] for points on the board: u = 0 at x = -side/2 (texture
    column 0), v = 0 at y = -side/2 (the texture's *last* row, since image row 0 is y = +side/2).
    """
    p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    return (p + side / 2.0) / side


def ring_cells(n: int) -> np.ndarray:
    """(4(n-1), 2) int (column, row) grid cells of a ring of n cells per side, clockwise from top-left."""
    k = np.arange(n - 1)
    top = np.c_[k, np.zeros_like(k)]
    right = np.c_[np.full_like(k, n - 1), k]
    bottom = np.c_[n - 1 - k, np.full_like(k, n - 1)]
    left = np.c_[np.zeros_like(k), n - 1 - k]
    return np.concatenate([top, right, bottom, left])


def _overlap(lo: np.ndarray, hi: np.ndarray, count: int, step: float) -> np.ndarray:
    """(count, C) fraction of each pixel [i*step, (i+1)*step) covered by each interval [lo_c, hi_c)."""
    edges = np.arange(count + 1) * step
    a = np.maximum(edges[:-1, None], lo[None, :])
    b = np.minimum(edges[1:, None], hi[None, :])
    return np.clip(b - a, 0.0, None) / step


class Board:
    """A square ring of square ArUco markers (``markers_per_side`` per edge, corners shared).

    Attributes (metres): ``side`` full board side, ``free_half_extent`` half side of the free square
    inside the ring (minus a safety margin), ``marker_ids`` (M,) int32, ``marker_corners`` (M, 4, 3)
    float64 board-frame corners ordered top-left, top-right, bottom-right, bottom-left as seen from
    above (cv2.aruco order), ``cv_board`` the matching ``cv2.aruco.Board``.
    """

    def __init__(self, cfg: BoardConfig):
        self.cfg = cfg
        name = cfg.dictionary.upper()
        if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
            raise ArgenError(f"board dictionary '{cfg.dictionary}' is not a cv2.aruco predefined dictionary "
                             "(e.g. DICT_4X4_100, DICT_5X5_250, DICT_APRILTAG_36h11)")
        self.dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        n = cfg.markers_per_side
        self.n_markers = 4 * (n - 1)
        n_dict = self.dictionary.bytesList.shape[0]
        if self.n_markers > n_dict:
            raise ArgenError(f"board needs {self.n_markers} markers ({n} per side) but {cfg.dictionary} "
                             f"has only {n_dict}; use fewer markers_per_side or a larger dictionary")
        ms, gap, margin = cfg.marker_size, cfg.marker_gap, cfg.margin
        self.pitch = ms + gap
        self.side = 2 * margin + n * ms + (n - 1) * gap
        self.free_half_extent = self.side / 2 - margin - ms - FREE_AREA_SAFETY
        if self.free_half_extent <= 0:
            raise ArgenError("board has no free central area: use more markers_per_side or a larger marker_gap")
        self.marker_ids = np.arange(self.n_markers, dtype=np.int32)
        self.cells = ring_cells(n)  # (M, 2) column, row of each marker in the ring grid (row 0 at the top)
        # top-left corner of each marker, measured from the board's left and top edges
        s0 = margin + self.cells[:, 0] * self.pitch
        t0 = margin + self.cells[:, 1] * self.pitch
        ds = np.array([0.0, ms, ms, 0.0])  # TL, TR, BR, BL
        dt = np.array([0.0, 0.0, ms, ms])
        x = s0[:, None] + ds[None, :] - self.side / 2
        y = self.side / 2 - (t0[:, None] + dt[None, :])
        self.marker_corners = np.stack([x, y, np.zeros_like(x)], axis=-1)
        self.cv_board = cv2.aruco.Board(self.marker_corners.astype(np.float32), self.dictionary,
                                        self.marker_ids.reshape(-1, 1))

    @classmethod
    def from_config(cls, cfg: BoardConfig) -> Board:
        """The board described by a template's ``board`` section."""
        return cls(cfg)

    @cached_property
    def detector(self) -> cv2.aruco.ArucoDetector:
        """An ArucoDetector for this board's dictionary with sub-pixel corner refinement."""
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        return cv2.aruco.ArucoDetector(self.dictionary, params)

    def marker_bits(self) -> np.ndarray:
        """(M, b+2, b+2) bool: True where marker m is black, one entry per cell including the border."""
        b = self.dictionary.markerSize + 2
        imgs = [cv2.aruco.generateImageMarker(self.dictionary, int(i), b, borderBits=1) for i in self.marker_ids]
        return np.stack(imgs) < 128

    def raster(self, px_per_m: float) -> np.ndarray:
        """(W, W) float32 black coverage in [0, 1] of the board at ~px_per_m, exact area anti-aliasing.

        W = round(side * px_per_m); the actual scale is W / side pixels per metre (see module doc).
        """
        W = max(int(round(self.side * px_per_m)), 1)
        bits = self.marker_bits()
        M, b, _ = bits.shape
        n = self.cfg.markers_per_side
        cell = self.cfg.marker_size / b
        # every cell boundary of every grid position, along one axis (same for rows and columns)
        start = self.cfg.margin + np.arange(n)[:, None] * self.pitch + np.arange(b)[None, :] * cell  # (n, b)
        lo = start.ravel()
        A = _overlap(lo, lo + cell, W, self.side / W).astype(np.float32)  # (W, n*b) pixel x cell overlap
        G = np.zeros((n * b, n * b), np.float32)  # rows = cell rows from the top, cols = cell columns
        for m, (c, r) in enumerate(self.cells):  # 4(n-1) small blocks
            G[r * b:(r + 1) * b, c * b:(c + 1) * b] = bits[m]
        return np.clip((A @ G) @ A.T, 0.0, 1.0)

    def texture(self, px_per_m: float | None = None) -> np.ndarray:
        """(W, W, 3) uint8 RGB image of the whole board: white background, black markers.

        px_per_m defaults to the config's ``texture_px_per_m``; W = round(side * px_per_m).
        """
        cov = self.raster(px_per_m or self.cfg.texture_px_per_m)
        g = np.round(255.0 * (1.0 - cov)).astype(np.uint8)
        return np.repeat(g[..., None], 3, axis=2)

    def print_image(self, dpi: int) -> np.ndarray:
        """(W, W) uint8 grey image at true print scale (W = side / 25.4 mm * dpi), with a size label.

        The label (dictionary, marker size in mm) goes into the bottom margin when it fits there
        without touching any marker; otherwise it is left out.
        """
        if dpi <= 0:
            raise ArgenError(f"print dpi must be positive, got {dpi}")
        ppm = dpi / INCH
        img = np.round(255.0 * (1.0 - self.raster(ppm))).astype(np.uint8)
        self._draw_label(img, img.shape[0] / self.side)
        return img

    def label_text(self) -> str:
        """The label printed in the margin."""
        c = self.cfg
        return (f"{c.dictionary}  marker {c.marker_size * 1000:g} mm  gap {c.marker_gap * 1000:g} mm  "
                f"board {self.side * 1000:g} mm")

    def _draw_label(self, img: np.ndarray, ppm: float) -> None:
        """Write the label into the bottom margin of ``img`` in place, if it fits clear of the markers."""
        margin_px = int(np.floor(self.cfg.margin * ppm))
        pad = max(2, margin_px // 6)
        target_h = margin_px - 2 * pad  # text height incl. descenders
        if target_h < 8:
            return
        font, text = cv2.FONT_HERSHEY_SIMPLEX, self.label_text()
        (w1, h1), base1 = cv2.getTextSize(text, font, 1.0, 1)
        scale = target_h / (h1 + base1)
        thick = max(1, int(round(scale * 1.5)))
        (w, h), base = cv2.getTextSize(text, font, scale, thick)
        H, W = img.shape
        x0 = int(W - int(np.ceil(self.cfg.margin * ppm)) - w)  # right-aligned with the ring's right edge
        y_base = H - pad - base
        top = y_base - h - thick
        first_black = H - margin_px  # first image row of the ring's bottom markers (rounded down)
        if x0 < pad or top <= first_black or w <= 0:
            return
        canvas = np.full_like(img, 255)
        cv2.putText(canvas, text, (x0, y_base), font, scale, 0, thick, cv2.LINE_AA)
        ink = canvas < 255
        near_marker = cv2.dilate((img < 250).astype(np.uint8), np.ones((2 * pad + 1,) * 2, np.uint8)) > 0
        if (ink & near_marker).any() or not ink.any():
            return
        np.minimum(img, canvas, out=img)

    def save_print(self, path: str | Path, dpi: int | None = None) -> Path:
        """Write the print image as a PNG with dpi metadata, so it prints at true size. Returns the path."""

        dpi = int(dpi or self.cfg.print_dpi)
        path = Path(path)
        if path.suffix.lower() != ".png":
            raise ArgenError(f"board print must be a .png file, got {path}")
        if not path.parent.is_dir():
            raise ArgenError(f"folder does not exist: {path.parent}")
        Image.fromarray(self.print_image(dpi)).save(path, dpi=(dpi, dpi))
        return path
