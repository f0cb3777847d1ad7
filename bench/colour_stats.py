"""How an object's colours look in a label file: over the points of its instances (at least --min-visib visible),
the mean and spread of each channel and the share of points with a channel at 0.98 or more (clipped). Compares a
real sensor's colours with a simulated capture's, e.g. the ycbv_real gelatin box against run.sh's capture:

    python bench/colour_stats.py data/ycbv_real.h5 --obj 8
    python bench/colour_stats.py data/ycbv_train.h5 --obj 8 --frames 200
"""

from __future__ import annotations

import argparse

import numpy as np

from argen.h5 import LabelFile


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("labels")
    ap.add_argument("--obj", type=int, required=True, help="object id")
    ap.add_argument("--frames", type=int, default=None, help="first N frames (default: all)")
    ap.add_argument("--min-visib", type=float, default=0.6)
    a = ap.parse_args()
    rgb, n = [], 0
    with LabelFile(a.labels) as lf:
        for i in range(lf.num_frames if a.frames is None else min(a.frames, lf.num_frames)):
            f = lf.frame(i)
            inst = f.instances
            for g in range(len(inst)):
                if int(inst.obj_id[g]) == a.obj and inst.visib_fract[g] >= a.min_visib:
                    rgb.append(np.asarray(f.features, np.float64)[np.asarray(f.instance) == g, 3:6])
                    n += 1
    if not rgb:
        raise SystemExit(f"{a.labels}: no instance of object {a.obj} at least {a.min_visib} visible")
    c = np.concatenate(rgb)
    print(f"{a.labels}: object {a.obj}, {n} instances, {len(c)} points: mean {np.round(c.mean(0), 3)}, "
          f"spread {np.round(c.std(0), 3)}, clipped (a channel >= 0.98) {100 * np.mean(c.max(1) >= 0.98):.1f} %")


if __name__ == "__main__":
    main()
