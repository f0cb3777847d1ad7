"""What a model finds in real frames that hold none of its objects: every detection there is a false alarm.

A real sensor's clutter, without a label file: each input is what `detector predict` takes (a BOP frame
SPLIT_DIR/SCENE_ID/IM_ID, or a depth PNG with --K / --depth-scale / --rgb), run with the model's own settings
(and ICP unless --no-icp) and its working volume (the points up to the depth its training frames had, unless
--max-depth). Prints one line per frame (the detections' names and scores) and the totals.

Usage: python bench/false_alarms.py CKPT INPUT [INPUT ...] [--K fx,fy,cx,cy --depth-scale S --rgb RGB.png]
       [--out DIR] [--no-icp] [--max-depth M] [--set sampling.density=D ...]

Example (none of the LineMOD objects is in these frames):
  python bench/false_alarms.py checkpoints/lm8.pt ../shared/data/ycbv_real/test/000000/{000001..000010}
  python bench/false_alarms.py checkpoints/lm8.pt ../shared/data/recordings/tum_desk/depth/000000.png \
      --K 525,525,319.5,239.5 --depth-scale 0.2 --rgb ../shared/data/recordings/tum_desk/rgb/000000.png
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

import torch

from detector.checkpoint import load_checkpoint
from detector.errors import DetectorError
from detector.infer import (checkpoint_geometry_config, checkpoint_max_depth, checkpoint_objects, checkpoint_poser,
                            missing_surfaces, split_sets)
from detector.net_dtype import resolve_net_dtype
from detector.predict import load_input, predict
from detector.stage1.predictor import network_predictor


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("ckpt", type=Path)
    ap.add_argument("inputs", nargs="+")
    ap.add_argument("--K", default=None, help="intrinsics of depth PNG inputs: fx,fy,cx,cy")
    ap.add_argument("--depth-scale", type=float, default=None, help="depth PNG value x scale = millimetres")
    ap.add_argument("--rgb", type=Path, default=None, help="colour image of a (single) depth PNG input")
    ap.add_argument("--out", type=Path, default=None, help="keep each frame's poses.json and poses.png here")
    ap.add_argument("--no-icp", action="store_true")
    ap.add_argument("--max-depth", type=float, default=None,
                    help="metres along z (default: the model's training volume, as detector predict)")
    ap.add_argument("--set", dest="sets", action="append", default=[],
                    help="a geometry, sampling or stage-2 inference (infer.*) setting of the model, "
                         "as detector predict --set")
    ap.add_argument("--net-dtype", default="auto", help="the networks' number format, as detector predict --net-dtype")
    a = ap.parse_args()
    torch.set_num_threads(2)
    try:
        sets, sampling, infer_sets = split_sets(a.sets)
        net_dtype = resolve_net_dtype(a.net_dtype)
        ckpt = load_checkpoint(a.ckpt, "cpu", sampling)
        cfg = checkpoint_geometry_config(ckpt, None, not a.no_icp, None, sets)
        objects, names = checkpoint_objects(ckpt)
        poser = checkpoint_poser(ckpt, objects, "cpu", 0, infer_sets, net_dtype)
    except DetectorError as e:
        raise SystemExit(f"false_alarms.py: {e}") from None
    if (warning := missing_surfaces(cfg, objects, a.ckpt)) is not None:
        print(f"warning: {warning}", file=sys.stderr)
    predictor = network_predictor(ckpt, 0, net_dtype=net_dtype)
    depth = checkpoint_max_depth(ckpt, a.max_depth)
    total = frames = 0
    with tempfile.TemporaryDirectory() as tmp:
        for spec in a.inputs:
            try:
                inp = load_input(spec, a.K, a.depth_scale, None, a.rgb, max_depth=depth)
            except DetectorError as e:  # e.g. nothing within the working volume: no frame to look at
                print(f"{spec}: skipped: {e}", flush=True)
                continue
            out = (a.out if a.out is not None else Path(tmp)) / re.sub(r"[^A-Za-z0-9_.-]+", "_", spec.strip("./"))
            res = predict(predictor, inp, objects, out, cfg, names, poser, depth, net_dtype)
            dets = res["detections"]
            total, frames = total + len(dets), frames + 1
            print(f"{spec}: {len(dets)} " + " ".join(f"{d['name']}:{d['score']:.2f}" for d in dets), flush=True)
    print(f"{total} detections in {frames} frames ({total / max(frames, 1):.2f} a frame), ICP {not a.no_icp}, "
          f"networks in {net_dtype}, "
          f"points up to {depth if depth is not None else 'any'} m")


if __name__ == "__main__":
    main()
