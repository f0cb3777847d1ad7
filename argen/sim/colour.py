"""The colour camera's own artefacts, applied to a simulated frame's colour image after rendering.

A real RGB-D sensor's colour image is not the renderer's: it is taken by a second camera whose registration to
the depth is off by a pixel or two, through a lens that blurs, and with sensor noise. Point features take their
colour from the pixel at the depth pixel, so near object edges a real frame's points carry the colours of what
lies beside them. Global colour changes (exposure, white balance, gamma) are left to the detector's training
augmentation (``detector.data.augment.camera_colour``), which draws them anew in every epoch.

Only the colour image changes: depth, masks and ground truth stay exactly as rendered.
"""

from __future__ import annotations

import cv2
import numpy as np

from argen.config import ColourConfig


def apply_colour(rgb: np.ndarray, cfg: ColourConfig, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Misregister, blur and add sensor noise to a colour image.

    rgb: (H, W, 3) uint8. Returns the new (H, W, 3) uint8 image and what was drawn: {"shift_px": (dx, dy) the
    colour image's shift against the depth in pixels, "blur_px": Gaussian sigma in pixels, "noise": the noise's
    standard deviation in [0, 1] units}.
    """
    if not cfg.enabled:
        return rgb, {}
    a = rng.uniform(0, 2 * np.pi)
    shift = rng.uniform(*cfg.shift_px) * np.array([np.cos(a), np.sin(a)])
    blur = float(rng.uniform(*cfg.blur_px))
    noise = float(rng.uniform(*cfg.noise))
    out = np.asarray(rgb, np.float32)
    M = np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]], np.float32)
    out = cv2.warpAffine(out, M, (out.shape[1], out.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if blur > 0.05:
        out = cv2.GaussianBlur(out, (0, 0), blur)
    out = out + rng.normal(0.0, noise * 255.0, out.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8), {"shift_px": [float(shift[0]), float(shift[1])],
                                                              "blur_px": blur, "noise": noise}
