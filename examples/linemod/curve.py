"""Plot RESULTS.md's time-to-accuracy curve: ADD(-S) at 10 % of the diameter against training minutes.

    .venv/bin/python examples/linemod/curve.py --out docs/img/time_to_accuracy.png \
        --stage2 5.0:17.4 15.2:37.2 37.5:66.3 --full 55.1:XX --full-icp 55.1:YY

--stage2 points are stage 2 alone on crops around the true centres jittered by 1.2 cm (bench/probe_crops.py, 25
test frames, no refinement) at stage-2 training minutes; --full / --full-icp are the whole two-stage model
(detector eval on the test set) at the total training minutes (stage 2 + stage 1).
"""

from __future__ import annotations

import argparse


def pairs(values: list[str]) -> list[tuple[float, float]]:
    return [tuple(float(x) for x in v.split(":")) for v in values or []]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--stage2", nargs="*", default=[])
    ap.add_argument("--full", nargs="*", default=[])
    ap.add_argument("--full-icp", nargs="*", default=[])
    ap.add_argument("--paper-net", nargs="*", default=[], help="the paper's single network (minutes:accuracy)")
    a = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4), dpi=100)
    for name, pts, style in (("stage 2 on true centres + 1.2 cm jitter", pairs(a.stage2), "o-"),
                             ("two-stage model, without refinement", pairs(a.full), "s"),
                             ("two-stage model, with ICP", pairs(a.full_icp), "D"),
                             ("paper's single network (cpu preset), with ICP", pairs(a.paper_net), "x")):
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], style, label=name)
    ax.axhline(90, color="0.7", lw=0.8, ls="--")
    ax.axvline(60, color="0.7", lw=0.8, ls=":")
    ax.set(xlabel="training minutes (2-core CPU)", ylabel="ADD(-S) at 10 % of the diameter (%)", ylim=(0, 100),
           xlim=(0, 70))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(a.out)


if __name__ == "__main__":
    main()
