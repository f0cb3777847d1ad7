"""How an object's colours look in a label file: over the points of its instances (at least --min-visib visible),
the mean and spread of each channel and the share of points with a channel at 0.98 or more (clipped). Compares a
real sensor's colours with a simulated capture's, e.g. the ycbv_real gelatin box against run.sh's capture:

    python bench/colour_stats.py data/ycbv_real.h5 --obj 8
    python bench/colour_stats.py data/ycbv_train.h5 --obj 8 --frames 200

With --models (a BOP models folder with vertex colours) it also sets each point beside the colour of the model's
nearest vertex at the true pose (``probe_crops.painted``; points more than 4 mm off the model surface are left out):
the 10th and 90th percentiles of each, and their rank (Spearman) correlation per channel, which no per-channel tone
curve changes:

    python bench/colour_stats.py data/ycbv_real.h5 --obj 8 --min-visib 0 --models ../shared/data/ycbv_real/models
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.stats import spearmanr

from argen.h5 import LabelFile
from probe_crops import painted


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("labels")
    ap.add_argument("--obj", type=int, required=True, help="object id")
    ap.add_argument("--frames", type=int, default=None, help="first N frames (default: all)")
    ap.add_argument("--min-visib", type=float, default=0.6)
    ap.add_argument("--models", default=None, help="BOP models folder: compare with the models' vertex colours")
    a = ap.parse_args()
    rgb, model, on, n, cache = [], [], [], 0, {}
    with LabelFile(a.labels) as lf:
        for i in range(lf.num_frames if a.frames is None else min(a.frames, lf.num_frames)):
            f = lf.frame(i)
            inst = f.instances
            paint, on_model = painted(f, a.models, cache) if a.models else (None, None)
            for g in range(len(inst)):
                if int(inst.obj_id[g]) == a.obj and inst.visib_fract[g] >= a.min_visib:
                    rows = np.asarray(f.instance) == g
                    rgb.append(np.asarray(f.features, np.float64)[rows, 3:6])
                    if paint is not None:
                        model.append(np.asarray(paint, np.float64)[rows, 3:6])
                        on.append(on_model[rows])
                    n += 1
    if not rgb:
        raise SystemExit(f"{a.labels}: no instance of object {a.obj} at least {a.min_visib} visible")
    c = np.concatenate(rgb)
    print(f"{a.labels}: object {a.obj}, {n} instances, {len(c)} points: mean {np.round(c.mean(0), 3)}, "
          f"spread {np.round(c.std(0), 3)}, clipped (a channel >= 0.98) {100 * np.mean(c.max(1) >= 0.98):.1f} %")
    if model:
        keep = np.concatenate(on)  # within 4 mm of the model surface
        c, m = c[keep], np.concatenate(model)[keep]
        rho = [spearmanr(c[:, k], m[:, k])[0] for k in range(3)]
        print(f"{len(c)} points on the model surface; 10th / 90th percentiles (R, G, B): points "
              f"{np.round(np.quantile(c, 0.1, 0), 2)} / "
              f"{np.round(np.quantile(c, 0.9, 0), 2)}, model {np.round(np.quantile(m, 0.1, 0), 2)} / "
              f"{np.round(np.quantile(m, 0.9, 0), 2)}; rank correlation with the model's colours {np.round(rho, 2)}")


if __name__ == "__main__":
    main()
