"""How much a model's accuracy depends on the colours it sees: evaluate a checkpoint on a label file with the
points' colours changed the way a real camera's differ from the renderer's (exposure, white balance, gamma, no
colour), in each stage or in both. Real frames are not available here; this bounds what a colour mismatch costs.

Usage: python bench/probe_colour.py CKPT LABELS [--frames N] [--change NAME ...] [--stage both|stage1|stage2]
                                    [--set geometry.KEY=VALUE | infer.KEY=VALUE ...]
(NAME: none, darker, brighter, warm, gamma, grey, zeros; default all). Prints one line per change: ADD(-S)@10 %
with and without ICP and F1@15 % (precision / recall), with the model's own settings (``--set`` over them, as
``detector eval --set``: e.g. stage 2 without its colour level, ``--set infer.colour_level=false``).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from detector.checkpoint import load_checkpoint
from detector.data.frames import open_label_file
from detector.evaluate import evaluate
from detector.errors import DetectorError
from detector.infer import checkpoint_geometry_config, checkpoint_objects, checkpoint_poser, split_sets
from detector.stage1.predictor import network_predictor

#: Colour changes of the (N,3) colours in [0, 1].
CHANGES = {
    "none": lambda c: c,
    "darker": lambda c: c * 0.7,  # exposure x0.7
    "brighter": lambda c: np.clip(c * 1.3, 0, 1),  # exposure x1.3
    "warm": lambda c: np.clip(c * np.array([1.15, 1.0, 0.85]), 0, 1),  # white balance
    "gamma": lambda c: c ** 0.7,
    "grey": lambda c: np.repeat(c.mean(1, keepdims=True), 3, 1),
    "zeros": lambda c: c * 0.0,  # a depth-only input
}


def recoloured(features: np.ndarray, change) -> np.ndarray:
    """A copy of features (N,9) with the colour columns changed."""
    out = np.array(features, dtype=np.float32, copy=True)
    out[:, 3:6] = change(out[:, 3:6].astype(np.float64)).astype(np.float32)
    return out


def recolouring_predictor(predictor, change):
    """``predictor`` run on frames whose colours are changed by ``change``."""

    def predict(frame):
        return predictor(SimpleNamespace(features=recoloured(frame.features, change), scene_id=frame.scene_id,
                                         im_id=frame.im_id))

    return predict


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("ckpt", type=Path)
    ap.add_argument("labels", type=Path)
    ap.add_argument("--frames", type=int, default=None, help="first N frames (default: all)")
    ap.add_argument("--change", nargs="*", default=list(CHANGES), choices=list(CHANGES))
    ap.add_argument("--stage", default="both", choices=["both", "stage1", "stage2"])
    ap.add_argument("--set", dest="sets", action="append", default=[],
                    help="geometry.KEY=VALUE or infer.KEY=VALUE over the model's settings")
    a = ap.parse_args()
    torch.set_num_threads(2)
    try:
        geometry, sampling, infer = split_sets(a.sets)
        ckpt = load_checkpoint(a.ckpt, "cpu", sampling)
        checkpoint_geometry_config(ckpt, None, True, None, geometry)
        checkpoint_poser(ckpt, checkpoint_objects(ckpt)[0], "cpu", 0, infer)
    except DetectorError as e:
        raise SystemExit(f"probe_colour.py: {e}") from None
    with open_label_file(a.labels) as lf:
        n = lf.num_frames if a.frames is None else min(a.frames, lf.num_frames)
    for name in a.change:
        change = CHANGES[name]
        cfg = checkpoint_geometry_config(ckpt, None, True, None, geometry)
        base_pred = network_predictor(ckpt, 0)
        poser = checkpoint_poser(ckpt, checkpoint_objects(ckpt)[0], "cpu", 0, infer)
        pred = recolouring_predictor(base_pred, change) if a.stage in ("both", "stage1") else base_pred
        if poser is not None and a.stage in ("both", "stage2"):
            def stage2(dets, features, timings=None, _s=poser, _c=change):
                return _s(dets, recoloured(features, _c), timings)
        else:
            stage2 = poser
        with tempfile.TemporaryDirectory() as out:
            s = evaluate(pred, a.labels, Path(out), icp=True, cfg=cfg, device="cpu", frames=list(range(n)),
                         progress=False, poser=stage2, bop19=False)  # ADD and F1 only
        f = s["f1"]["icp"]
        print(f"{name:9s} {a.stage}: ADD(-S)@10 % with ICP {100 * s['mean']['icp']['0.10']:.1f}, without "
              f"{100 * s['mean']['noicp']['0.10']:.1f}; F1@15 % {100 * f['f1']:.1f} (P {100 * f['precision']:.1f} / "
              f"R {100 * f['recall']:.1f})", flush=True)


if __name__ == "__main__":
    main()
