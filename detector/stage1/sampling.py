"""Stage 1's sampling at inference (:class:`SamplingConfig`): how many points a frame gives the network, in how many
passes, and how each sampling level's farthest points are found. A model file stores these settings
(``detector.checkpoint``); :func:`detector.stage1.predictor.network_predictor` samples by them."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from detector.errors import DetectorError


#: The values of ``sampling.fps`` (:class:`SamplingConfig`).
FPS_CHOICES = ("trained", "tree")


@dataclass
class SamplingConfig:
    """How stage 1 samples a frame at inference, against how it trained. density: the points drawn from a frame
    and the keypoints (the first sampling level's points, where the network predicts) are both this many times the
    training's, rounded up to a multiple of 64; the neighbourhoods keep their radii. Above 1 a small object gets
    more predictions (RESULTS.md, ``checkpoints/lm8.pt``) for some milliseconds a frame (BENCHMARKS.md), but the
    network meets neighbourhoods denser than it trained on. passes: stage 1 runs on this many samplings of the frame,
    each drawn as a single pass draws (another seed each; the first is the single pass's), in one batch, and their
    predictions are pooled: a small object gets that many times the predictions while each pass sees the density
    the network trained on (:func:`detector.stage1.predictor.network_predictor`). A centre's ``geometry.min_votes``
    counts the votes of all passes. fps: how each sampling level's farthest points are found on a CPU (a GPU computes
    them in torch, :mod:`detector.stage1.ops`): ``"trained"`` as in training (fpsample's FPS loop from the first
    point on clouds of up to 4096 points, its tree-based FPS on larger ones) or ``"tree"`` (the tree-based FPS on
    every level: as well spread points from another first point, about 9 ms sooner a pass at 4096 points;
    BENCHMARKS.md)."""

    density: float = 1.0
    passes: int = 1
    fps: str = "trained"

    def __post_init__(self):
        try:
            if isinstance(self.density, bool):
                raise TypeError
            self.density = float(self.density)
        except (TypeError, ValueError):
            raise DetectorError(f"sampling.density must be a number, got {self.density!r}") from None
        if not 0.25 <= self.density <= 8:
            raise DetectorError(f"sampling.density must be in [0.25, 8], got {self.density}")
        try:
            if isinstance(self.passes, (bool, str)) or float(self.passes) != int(self.passes):
                raise TypeError
        except (TypeError, ValueError, OverflowError):  # not a number, nan, inf, 1.5
            raise DetectorError(f"sampling.passes must be a whole number, got {self.passes!r}") from None
        self.passes = int(self.passes)
        if not 1 <= self.passes <= 8:
            raise DetectorError(f"sampling.passes must be in [1, 8], got {self.passes}")
        if self.fps not in FPS_CHOICES:
            raise DetectorError(f"sampling.fps must be one of {', '.join(FPS_CHOICES)}, got {self.fps!r}")

    @classmethod
    def from_dict(cls, d: dict | None) -> "SamplingConfig":
        """From a model file's or a --set's settings; a one-line DetectorError for an unknown key."""
        d = dict(d or {})
        unknown = set(d) - {f.name for f in fields(cls)}
        if unknown:
            raise DetectorError(f"unknown sampling option '{sorted(unknown)[0]}' (sampling.density, sampling.passes, "
                                "sampling.fps)")
        return cls(**d)

    def scaled(self, count: int) -> int:
        """``count`` (points or keypoints of training) at this density: itself at 1, else a multiple of 64."""
        if self.density == 1:
            return int(count)
        return max(64, 64 * math.ceil(round(count * self.density / 64, 9)))  # 3200 x 1.1 is 3520, not 3584
