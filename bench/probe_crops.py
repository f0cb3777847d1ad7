"""Stage-2 check on ground-truth-centred crops: ADD(-S) of crop poses on a label file, with the centre jittered
like stage 1's error. Usage: python bench/probe_crops.py CKPT LABELS [--frames N] [--jitter M] [--paint-models DIR]

--paint-models DIR (a BOP models folder with vertex colours, e.g. ../shared/data/ycbv_real/models) is a diagnosis:
each point within 4 mm of an annotated object's surface at its true pose takes the colour of the model's nearest
vertex, so stage 2 sees the real depth with the model's own colours: what is left wrong is not the colours' fault."""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from scipy.spatial import cKDTree

from argen.bop import model_path, read_mesh
from argen.h5 import LabelFile
from detector.evaluation.metrics import pose_error
from detector.geometry.types import ObjectInfo
from detector.stage2.crops import CropConfig
from detector.stage2.network import build_stage2_net
from detector.stage2.poser import PoserConfig, crop_predictions, pose_from_crop
from detector.training.checkpoint_file import read_checkpoint


def painted(frame, models_dir: str, cache: dict) -> tuple[np.ndarray, np.ndarray]:
    """A copy of frame.features (N,9) whose points within 4 mm of an annotated object's model surface at its true pose
    take the colour of the model's nearest vertex (in [0, 1]), and which points those are ((N,) bool).
    models_dir: BOP models folder (mm, vertex colours)."""
    out = np.array(frame.features, dtype=np.float32, copy=True)
    on_model = np.zeros(len(out), bool)
    xyz = np.asarray(out[:, :3], np.float64)
    inst = frame.instances
    for g in range(len(inst)):
        oid = int(inst.obj_id[g])
        if oid not in cache:
            path = model_path(models_dir, oid)
            mesh = read_mesh(path)  # metres
            colours = getattr(mesh.visual, "vertex_colors", None)
            if colours is None or len(colours) != len(mesh.vertices):
                raise SystemExit(f"{path}: no vertex colours")
            cache[oid] = (np.asarray(mesh.vertices, np.float64), np.asarray(colours)[:, :3] / 255.0)
        v, col = cache[oid]
        d, j = cKDTree(v @ np.asarray(inst.R[g]).T + np.asarray(inst.t[g])).query(xyz)
        near = d < 0.004
        out[near, 3:6] = col[j[near]]
        on_model |= near
    return out, on_model


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("ckpt")
    ap.add_argument("labels")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--jitter", type=float, default=0.012)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--verify", type=int, default=None, help="PoserConfig.verify (default: its default)")
    ap.add_argument("--paint-models", default=None, help="BOP models folder: the true objects' points take its "
                    "vertex colours (a diagnosis, module docstring)")
    a = ap.parse_args()
    torch.set_num_threads(2)
    part = read_checkpoint(a.ckpt)["stage2"]  # a stage-2 run's last.pt or a two-stage model.pt
    net = build_stage2_net(part, a.ckpt).eval()
    ccfg = CropConfig.from_dict(part["crop_config"])
    pcfg = PoserConfig() if a.verify is None else PoserConfig(verify=a.verify)
    ids = part["class_ids"]
    rng = np.random.default_rng(a.seed)
    colours: dict = {}
    ok, n, errs, per, t_net = {}, {}, [], {}, 0.0
    with LabelFile(a.labels) as lf:
        tab = lf.objects
        objs = ObjectInfo.from_table(tab)
        for i in range(min(a.frames, lf.num_frames)):
            f = lf.frame(i)
            inst = f.instances
            features = f.features if a.paint_models is None else painted(f, a.paint_models, colours)[0]
            for g in range(len(inst)):
                oid = int(inst.obj_id[g])
                if oid not in ids or inst.visib_fract[g] < 0.1:
                    continue
                m = tab.index(oid)
                dia = float(tab.diameters[m])
                c = inst.control_points[g][8] + np.clip(rng.normal(0, a.jitter, 3), -2.5 * a.jitter, 2.5 * a.jitter)
                t0 = time.perf_counter()
                pred = crop_predictions(net, features, c[None], np.array([ids.index(oid)]), np.array([dia]), ccfg,
                                        part["normalisation"], seed=i)[0]
                res = None
                if pred is not None:
                    rows, prob, mxyz = pred
                    res = pose_from_crop(features[rows, :3].astype(np.float64), prob, mxyz, dia, pcfg, rng,
                                         objs.surface(oid))
                    if res is not None and pcfg.recentre:
                        R, t = res[0], res[1]
                        c2 = R @ tab.control_points[m][8] + t
                        pred = crop_predictions(net, features, c2[None], np.array([ids.index(oid)]), np.array([dia]),
                                                ccfg, part["normalisation"], seed=i)[0]
                        if pred is not None:
                            rows, prob, mxyz = pred
                            res = pose_from_crop(features[rows, :3].astype(np.float64), prob, mxyz, dia, pcfg, rng,
                                                 objs.surface(oid)) or res
                t_net += time.perf_counter() - t0
                e = np.inf if res is None else pose_error(tab.model_points[m], bool(tab.symmetric[m]), inst.R[g],
                                                          inst.t[g], res[0], res[1])
                errs.append(e / dia)
                name = tab.names[m]
                per.setdefault(name, []).append(e / dia)
    errs = np.array(errs)
    print(f"{len(errs)} instances, {1000 * t_net / max(len(errs), 1):.1f} ms per crop pose")
    for name, v in sorted(per.items()):
        v = np.array(v)
        print(f"  {name:12s} n={len(v):4d}  ADD@10% {100 * np.mean(v < 0.1):5.1f}  @30% {100 * np.mean(v < 0.3):5.1f}  "
              f"median error {np.median(v):.2f} of the diameter")
    print(f"ALL ADD(-S)@10% {100 * np.mean(errs < 0.1):.1f}  @15% {100 * np.mean(errs < 0.15):.1f}  "
          f"@30% {100 * np.mean(errs < 0.3):.1f}")


if __name__ == "__main__":
    main()
