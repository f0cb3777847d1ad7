"""The colour level of a crop: stage 2 reads colour as the renderer gave it in training, and another camera's
exposure scales every colour of a frame. The level each object's visible points had in the training frames is kept
with the model (:func:`colour_levels`); at inference the first crop's foreground tells the level the frame shows of
the object asked about, and the later crops are cut from colours brought back to the training level
(:func:`level_gain`, :func:`levelled`). One gain for the three channels: a white balance is left alone (a per-channel
gain measured worse on the simulated captures, RESULTS.md). Colours are RGB in [0, 1]."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from argen.h5 import LabelFile

#: Fewest foreground points of the first crop for its level to be measured (fewer: the crop is left as it is).
MIN_POINTS = 30

#: A gain outside these bounds is not applied (the crop is left as it is): a level that far off says more likely that
#: the first crop's foreground is not the object (clutter) than that the camera's exposure is that far off. Applying
#: it, even clipped, made real clutter look like the asked object: in the real frames without LineMOD objects
#: ``lm8.pt``'s false detections rose from 3 + 0 to 5 + 1 with the gain clipped to 0.5-2 and to 3 + 1 clipped to
#: 0.67-1.5, and stayed 3 + 0 with these bounds (RESULTS.md). The training's own frames put an object's level within
#: about 0.13 of its median in log units.
GAIN_BOUNDS = (0.6, 1.7)

#: colour_levels reads at most this many frames of a label file (evenly spread), and counts an instance with at least
#: this many labelled points.
LEVEL_FRAMES, LEVEL_INSTANCE_POINTS = 400, 100


def colour_levels(label_path: str | Path, object_ids: Sequence[int], frames: int = LEVEL_FRAMES,
                  min_points: int = LEVEL_INSTANCE_POINTS) -> list[list[float] | None]:
    """Each object's colour level in a label file: the median over its instances (those with at least
    ``min_points`` labelled points, in at most ``frames`` frames evenly spread over the file) of the mean colour of
    the instance's labelled points, (3,) RGB in [0, 1]; None for an object with no such instance. Returns one entry
    per ``object_ids`` entry, in that order (plain lists: a model file's field)."""
    means: dict[int, list[np.ndarray]] = {int(o): [] for o in object_ids}
    with LabelFile(label_path) as lf:
        n = lf.num_frames
        for i in sorted(set(np.linspace(0, n - 1, min(frames, n)).astype(int).tolist())) if n else []:
            f = lf.frame(i)
            instance = np.asarray(f.instance)
            for g, oid in enumerate(np.asarray(f.instances.obj_id)):
                if int(oid) not in means:
                    continue
                rows = np.flatnonzero(instance == g)
                if len(rows) >= min_points:
                    means[int(oid)].append(np.asarray(f.features[rows, 3:6], np.float64).mean(axis=0))
    return [np.median(np.stack(means[int(o)]), axis=0).tolist() if means[int(o)] else None for o in object_ids]


def level_gain(observed: np.ndarray, level: Sequence[float] | None) -> float:
    """The gain that brings a crop's foreground colours ``observed`` (n,3) to the object's training ``level`` (3,):
    the ratio of their mean luminances (the mean of the three channels); 1 where it is outside :data:`GAIN_BOUNDS`,
    the level is unknown, the foreground has fewer than :data:`MIN_POINTS` points or either side is black. Exact for
    an exposure: colours x e give 1 / e times the gain of the colours (within the bounds)."""
    observed = np.asarray(observed, np.float64).reshape(-1, 3)
    if level is None or len(observed) < MIN_POINTS:
        return 1.0
    seen, want = float(observed.mean()), float(np.mean(level))
    if seen < 1e-3 or want < 1e-3:
        return 1.0
    gain = want / seen
    return float(gain) if GAIN_BOUNDS[0] <= gain <= GAIN_BOUNDS[1] else 1.0


def levelled(features: np.ndarray, gain: float) -> np.ndarray:
    """A float32 copy of frame features (n,9) (colour columns 3:6 in [0, 1]) with the colours times ``gain``,
    clipped to [0, 1]."""
    out = np.array(features, dtype=np.float32, copy=True)
    if gain != 1.0:
        out[:, 3:6] = np.clip(out[:, 3:6] * np.float32(gain), 0.0, 1.0)
    return out
