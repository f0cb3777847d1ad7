"""Inference time per frame, per stage (sampling, network, voting, Kabsch, stage 2, ICP, the checks), on CPU or GPU.

A two-stage checkpoint (``--checkpoint checkpoints/lm8.pt``) is timed end to end on its own predictions: the
median per stage and the median of whole frames (ICP included) over ``--frames`` frames after a warm-up.

Usage: .venv/bin/python bench/bench_infer.py [--data FILE.h5] [--checkpoint CKPT] [--preset cpu paper]
                                             [--frames 5] [--device cpu|cuda] [--threads N]
                                             [--net-dtype auto|float32|bfloat16]
                                             [--set geometry.KEY=VALUE ...] [--set sampling.density=D]
                                             [--set infer.KEY=VALUE ...]

``--net-dtype`` is the networks' number format, as ``detector eval --net-dtype`` (default auto: bfloat16 on a CPU
that multiplies it in hardware); the output line records the one used.

``--set`` changes the checkpoint's geometry and sampling settings as ``detector eval --set`` does (e.g. the
inference without the depth check and the other classes: ``--set geometry.depth_check=false --set
geometry.other_classes=2``; stage 1 drawing as many points as it trained on: ``--set sampling.density=1``; with the
training's farthest point sampling instead of the tree-based one: ``--set sampling.fps=trained``).

Sampling + network: a checkpoint (or a randomly initialised network of each ``--preset``, same cost) on the
label file's frames (median over frames after one warm-up). A random network's output is noise, so the
geometry (voting, Kabsch, ICP) is timed on the file's ground-truth labels instead (``oracle_predictor``
sampled to the network's point count): realistic instance counts and supports. Without ``--data`` a
3-frame noise-free capture-sim dataset of the built-in objects is made and labelled in a temporary folder.
The target is the paper's 6 fps (166 ms per frame), which it reached on a TITAN XP GPU.

Measured here (2-core shared CPU, --threads 1, noisy LineMOD capture of 4 objects, 30,000 points per frame,
3.2 detections per frame), ms per frame: cpu preset (4096 points) sampling 23, network 32, voting 2, Kabsch 1,
ICP 17 = 76 ms (13 fps; 17 fps without ICP); paper preset (16384 points) 288 + 569 + 3 + 1 + 25 = 887 ms
(1.1 fps). With --threads 2 while other jobs ran, the network took 20x longer (oversubscription).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path


def make_data(tmp: Path) -> Path:
    """A tiny labelled capture-sim dataset (3 frames, built-in objects, no noise)."""
    from typer.testing import CliRunner

    from argen.cli.app import app
    from argen.label import LabelConfig, LabelRequest, run_label

    r = CliRunner().invoke(app, ["capture-sim", "--frames", "3", "--noise", "none", "--out", str(tmp / "ds"),
                                 "--seed", "1", "--quiet"])
    if r.exit_code != 0:
        raise SystemExit(r.output)
    out = tmp / "bench.h5"
    run_label(LabelRequest(dataset=tmp / "ds", split="train_pbr", out=out, progress=False, cfg=LabelConfig()))
    return out


def network_times(ckpt, frames: list, device: str, net_dtype: str = "float32") -> dict[str, float]:
    """Median seconds of "sampling" and "network" over frames (first frame is a warm-up)."""
    from detector.stage1.predictor import network_predictor

    pred = network_predictor(ckpt, seed=0, device=device, net_dtype=net_dtype)
    pred(frames[0])
    runs = [pred(f).timings for f in frames]
    return {k: statistics.median(r[k] for r in runs) for k in ("sampling", "network")}


def pose_times(frames: list, objects, num_points: int) -> dict[str, float]:
    """Median seconds of voting, Kabsch and ICP per frame on ground-truth predictions, and detections per frame."""
    from detector.geometry.types import GeometryConfig
    from detector.infer import estimate
    from detector.stage1.predictor import oracle_predictor

    pred = oracle_predictor(num_points=num_points, seed=0)
    cfg = GeometryConfig(icp=True)
    estimate(pred(frames[0]), objects, cfg, {}, frames[0].features[:, :3])
    runs, dets = [], []
    for f in frames:
        t = {}
        d, _ = estimate(pred(f), objects, cfg, t, f.features[:, :3])
        runs.append(t)
        dets.append(len(d))
    out = {k: statistics.median(r.get(k, 0.0) for r in runs) for k in ("voting", "kabsch", "icp")}
    out["detections"] = statistics.mean(dets)
    return out


def two_stage_times(ck, frames: list, device: str, sets: list[str] | None = None,
                    infer_sets: dict | None = None, net_dtype: str = "float32") -> dict[str, float]:
    """A two-stage checkpoint end to end on real predictions: median seconds per stage and of the whole frame
    (sampling, network, voting, stage 2, ICP, depth check, colour check with the model's own geometry settings, ``sets`` over
    them), detections per frame and stage 2's crops per frame (the stage-1 detections and their other-class copies
    it poses); net_dtype: the networks' number format, resolved (detector.net_dtype)."""
    from detector.infer import (checkpoint_geometry_config, checkpoint_objects, checkpoint_poser, estimate,
                                missing_surfaces)
    from detector.report import STAGES
    from detector.stage1.predictor import network_predictor

    objects = checkpoint_objects(ck)[0]
    cfg = checkpoint_geometry_config(ck, None, True, sets=sets)
    if (warning := missing_surfaces(cfg, objects, "the model")) is not None:
        print(f"warning: {warning}", file=sys.stderr)
    pred = network_predictor(ck, seed=0, device=device, net_dtype=net_dtype)
    poser = checkpoint_poser(ck, objects, device, 0, infer_sets, net_dtype)
    runs, dets, crops = [], [], []

    def counted(found, features, timings=None):
        crops.append(len(found))
        return poser(found, features, timings)

    for k, f in enumerate([frames[0], *frames]):  # the first is a warm-up
        t0 = time.perf_counter()
        p = pred(f)
        t = dict(p.timings)
        d, r = estimate(p, objects, cfg, t, f.features[:, :3], counted, f.features)
        t["total"] = time.perf_counter() - t0
        if k:
            runs.append(t)
            dets.append(len(r))
    out = {s: statistics.median(r.get(s, 0.0) for r in runs) for s in (*STAGES, "total")}
    out["detections"] = statistics.mean(dets)
    out["crops"] = statistics.mean(crops[1:])  # after the warm-up
    return out


def random_checkpoint(preset: str, objects_dict: dict, device: str):
    """A Checkpoint of a randomly initialised network of ``preset`` (its train preset's point count)."""
    import torch

    from detector.checkpoint import Checkpoint
    from detector.data.augment import NORMALISATION
    from detector.stage1.network import PointNet2
    from detector.stage1.train import build_model_config, make_config

    cfg = make_config(preset, {})
    mcfg = build_model_config(cfg)
    torch.manual_seed(0)
    model = PointNet2(mcfg, num_classes=len(objects_dict["ids"])).to(device).eval()
    return Checkpoint(model=model, model_config=mcfg, class_ids=list(objects_dict["ids"]), objects=objects_dict,
                      num_points=cfg.num_points, step=0, extra={}, normalisation=dict(NORMALISATION))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path)
    ap.add_argument("--checkpoint", type=Path)
    ap.add_argument("--preset", nargs="+", default=["cpu"])
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    ap.add_argument("--net-dtype", default="auto",
                    help="the networks' number format, as detector eval's --net-dtype: auto, float32 or bfloat16")
    ap.add_argument("--set", dest="sets", action="append", default=[],
                    help="a geometry, sampling or stage-2 inference setting of the checkpoint, "
                         "geometry.KEY=VALUE, sampling.density=D, sampling.passes=N, sampling.fps=trained|tree or "
                         "infer.KEY=VALUE (two-stage checkpoints)")
    args = ap.parse_args()

    import torch

    from argen.h5 import LabelFile
    from detector.checkpoint import load_checkpoint
    from detector.data.frames import object_table_dict
    from detector.geometry.types import ObjectInfo
    from detector.errors import DetectorError
    from detector.infer import checkpoint_geometry_config, checkpoint_objects, checkpoint_poser, split_sets
    from detector.net_dtype import resolve_net_dtype

    if args.threads:
        torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data or make_data(Path(tmp))
        with LabelFile(data) as lf:
            frames = [lf.frame(i % lf.num_frames) for i in range(max(args.frames, 2))]
            objects_dict = object_table_dict(lf.objects)
            objects = ObjectInfo.from_table(lf.objects)
        results = []
        try:
            geometry_sets, sampling, infer_sets = split_sets(args.sets)
            net_dtype = resolve_net_dtype(args.net_dtype, args.device)
            if sampling and not args.checkpoint:
                raise DetectorError("--set sampling.* needs --checkpoint (the presets' random networks sample as built)")
            ckpts = [("checkpoint", load_checkpoint(args.checkpoint, args.device, sampling))] if args.checkpoint else \
                [(p, random_checkpoint(p, objects_dict, args.device)) for p in args.preset]
            for _, ck in ckpts:  # a bad --set geometry.* or infer.* is a one-line error before any timing
                if ck.stage2_net is not None:
                    checkpoint_geometry_config(ck, None, True, sets=geometry_sets)
                    checkpoint_poser(ck, checkpoint_objects(ck)[0], args.device, 0, infer_sets)
                elif infer_sets:
                    raise DetectorError("--set infer.* needs a two-stage --checkpoint")
        except DetectorError as e:
            raise SystemExit(f"bench_infer.py: {e}") from None
        for name, ck in ckpts:
            if ck.stage2_net is not None:  # a two-stage model: its whole pipeline on its own predictions
                t = two_stage_times(ck, frames, args.device, geometry_sets, infer_sets, net_dtype)
                ms = {k: round(1000 * v, 1) for k, v in t.items() if k not in ("detections", "crops")}
                res = {"model": f"{name} (two-stage)", "device": args.device, "net_dtype": net_dtype,
                       "threads": torch.get_num_threads(),
                       "sampling": ck.sampling_used,
                       "frame_points": int(statistics.mean(len(f.features) for f in frames)),
                       "detections_per_frame": t["detections"], "stage2_crops_per_frame": t["crops"], "ms": ms,
                       "fps": round(1000 / ms["total"], 2)}
                results.append(res)
                print(json.dumps(res), flush=True)
                continue
            net = network_times(ck, frames, args.device, net_dtype)
            pose = pose_times(frames, objects, ck.num_points)
            ms = {k: 1000 * v for k, v in {**net, **{k: pose[k] for k in ("voting", "kabsch", "icp")}}.items()}
            ms["total_no_icp"] = sum(ms[k] for k in ("sampling", "network", "voting", "kabsch"))
            ms["total"] = ms["total_no_icp"] + ms["icp"]
            res = {"model": name, "device": args.device, "net_dtype": net_dtype, "threads": torch.get_num_threads(),
                   "num_points": ck.num_points, "frame_points": int(statistics.mean(len(f.features) for f in frames)),
                   "detections_per_frame": pose["detections"], "ms": {k: round(v, 1) for k, v in ms.items()},
                   "fps": round(1000 / ms["total"], 2), "fps_no_icp": round(1000 / ms["total_no_icp"], 2)}
            results.append(res)
            print(json.dumps(res), flush=True)
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    print(f"# {started}: per-stage medians over {len(frames)} frames; target 166 ms (6 fps)")


if __name__ == "__main__":
    main()
