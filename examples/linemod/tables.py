"""Print the RESULTS.md tables of the LineMOD study from `detector eval` reports, with the paper's numbers.

    .venv/bin/python examples/linemod/tables.py reports/lm_test/report.json reports/lchf_test/report.json \
        [--single-shot reports/lm_test_tau0/report.json] [--run runs/lm_cpu]

The paper's numbers (Liu et al., Tables II-IV and the LC-HF table) are for the real LineMOD / LC-HF test
images; ours are for a synthetic held-out capture, so the columns are not the same test.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

#: The paper's Table II ("OURS" columns): ADD at 10 % of the diameter without / with ICP, in %.
PAPER_TABLE_II = {"ape": (53.2, 57.7), "can": (78.4, 96.8), "cat": (63.4, 66.9), "driller": (68.8, 71.7),
                  "duck": (39.7, 43.7), "eggbox": (62.1, 70.2), "glue": (74.6, 80.1), "holepuncher": (50.1, 75.8)}
PAPER_AVERAGE_13 = (63.1, 70.4)  # over the paper's 13 LineMOD objects
PAPER_TABLE_III = {"0.10": 63.1, "0.15": "over 90 (text)", "0.30": 93.47}
PAPER_LCHF_F1 = 0.892


def pct(v) -> str:
    return "–" if v is None else f"{100 * v:.1f}"


def table_ii(rep: dict, single: dict | None = None) -> str:
    """Table II layout; ``single``: a report of the paper's single-shot network, shown beside ours."""
    head = "| object | test instances | ours w/o refinement | ours with ICP |"
    if single:
        head += " single-shot w/o | single-shot with ICP |"
    rows = [head + " paper w/o | paper with ICP |", "|---|---:|---:|---:|" + ("---:|---:|" if single else "")
            + "---:|---:|"]
    by_name = {o["name"]: o for o in single["objects"]} if single else {}

    def cells(o: dict | None) -> str:
        if o is None:
            return " – | – |"
        icp = o["add"]["icp"]["0.10"] if o["add"]["icp"] else None
        return f" {pct(o['add']['noicp']['0.10'])} | {pct(icp)} |"

    for o in rep["objects"]:
        p = PAPER_TABLE_II.get(o["name"], (None, None))
        row = f"| {o['name']}{'*' if o['symmetric'] else ''} | {o['num_gt']} |" + cells(o)
        if single:
            row += cells(by_name.get(o["name"]))
        rows.append(row + f" {p[0] if p[0] is not None else '–'} | {p[1] if p[1] is not None else '–'} |")
    m = rep["mean"]
    mine = [v for k, v in PAPER_TABLE_II.items() if k in {o["name"] for o in rep["objects"]}]
    avg8 = tuple(round(sum(v[i] for v in mine) / len(mine), 1) for i in (0, 1)) if mine else ("–", "–")
    row = (f"| **average** | {sum(o['num_gt'] for o in rep['objects'])} | **{pct(m['noicp']['0.10'])}** | "
           f"**{pct(m['icp']['0.10']) if m.get('icp') else '–'}** |")
    if single:
        sm = single["mean"]
        row += f" {pct(sm['noicp']['0.10'])} | {pct(sm['icp']['0.10']) if sm.get('icp') else '–'} |"
    rows.append(row + f" {avg8[0]} ({PAPER_AVERAGE_13[0]} over 13) | {avg8[1]} ({PAPER_AVERAGE_13[1]} over 13) |")
    return "\n".join(rows)


def table_iii(rep: dict) -> str:
    keys = ["0.10", "0.15", "0.30"]
    rows = ["| | " + " | ".join(f"{int(float(k) * 100)} %" for k in keys) + " |", "|---|" + "---:|" * len(keys)]
    for o in rep["objects"]:
        rows.append(f"| {o['name']} | " + " | ".join(pct(o["add"]["noicp"][k]) for k in keys) + " |")
    rows.append("| **ours, average** | " + " | ".join(f"**{pct(rep['mean']['noicp'][k])}**" for k in keys) + " |")
    if rep["mean"].get("icp"):
        rows.append("| ours with ICP, average | " + " | ".join(pct(rep["mean"]["icp"][k]) for k in keys) + " |")
    rows.append("| paper, average (13 objects) | " + " | ".join(str(PAPER_TABLE_III[k]) for k in keys) + " |")
    return "\n".join(rows)


def f1_table(rep: dict) -> str:
    key = "icp" if rep["icp"] else "noicp"
    rows = ["| object | detections | instances | precision | recall | F1 |", "|---|---:|---:|---:|---:|---:|"]
    for o in rep["objects"]:
        f = o["f1"][key]
        if f["num_gt"] or f["num_det"]:
            rows.append(f"| {o['name']} | {f['num_det']} | {f['num_gt']} | {pct(f['precision'])} | {pct(f['recall'])} | "
                        f"{pct(f['f1'])} |")
    f = rep["f1"][key]
    rows.append(f"| **all** | {f['num_det']} | {f['num_gt']} | {pct(f['precision'])} | {pct(f['recall'])} | "
                f"**{pct(f['f1'])}** |")
    rows.append(f"| paper, LC-HF average | | | | | {100 * PAPER_LCHF_F1:.1f} |")
    return "\n".join(rows)


def timing(rep: dict) -> str:
    rows = ["| stage | ms per frame |", "|---|---:|"]
    rows += [f"| {k} | {v:.1f} |" for k, v in rep["timing_ms"].items() if k != "total"]
    rows.append(f"| **total** | **{rep['timing_ms']['total']:.1f}** ({rep['fps']:.2f} fps; paper 6 fps on a TITAN XP) |")
    return "\n".join(rows)


def training(run: Path) -> str:
    from detector.training.metrics_log import read_metrics

    rows = read_metrics(run / "metrics.csv")
    last = rows[-50:]
    mean = {k: sum(r[k] for r in last) / len(last) for k in ("loss", "cls", "offset", "conf", "acc")}
    rate = sorted(r["steps_per_s"] for r in rows)[len(rows) // 2]
    return (f"{len(rows)} steps ({rows[-1]['epoch']:.1f} epochs), median {rate:.2f} steps/s, "
            f"mean of the last 50 steps: loss {mean['loss']:.3f} (cls {mean['cls']:.3f}, offset {mean['offset']:.3f}, "
            f"conf {mean['conf']:.4f}), keypoint accuracy {mean['acc']:.3f}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("lm", type=Path, help="report.json of the linemod-template test set (eval with --icp)")
    ap.add_argument("lchf", type=Path, nargs="?", help="report.json of the lchf-template test set")
    ap.add_argument("--run", type=Path, help="training run folder (metrics.csv)")
    ap.add_argument("--single-shot", type=Path, help="report.json of the paper's single-shot network on the same "
                    "linemod test set (eval with --icp), shown beside ours")
    args = ap.parse_args()
    lm = json.loads(args.lm.read_text())
    single = json.loads(args.single_shot.read_text()) if args.single_shot else None
    print(f"### ADD(-S) at 10 % of the diameter (Table II layout), {lm['num_frames']} frames, tau "
          f"{lm['config']['tau']}\n\n{table_ii(lm, single)}\n")
    print(f"### Thresholds without refinement (Table III layout)\n\n{table_iii(lm)}\n")
    if args.lchf:
        lchf = json.loads(args.lchf.read_text())
        print(f"### LC-HF-style F1 at 15 % ({lchf['num_frames']} frames, tau {lchf['config']['tau']}, "
              f"{'with' if lchf['icp'] else 'without'} ICP)\n\n{f1_table(lchf)}\n")
    print(f"### Time per stage ({lm['device']})\n\n{timing(lm)}\n")
    if args.run:
        print(f"### Training\n\n{training(args.run)}\n")


if __name__ == "__main__":
    main()
