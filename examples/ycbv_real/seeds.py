"""Mean and range over sampling seeds of `detector eval` reports named NAME-SEED in one folder (run.sh step 6c).

    python examples/ycbv_real/seeds.py reports/ycbv3_real/seeds

Prints, per NAME, ADD(-S)@10 % without / with ICP (mean, range), F1 with ICP and BOP19 AR (mean, range), and each
object's mean ADD(-S) without / with ICP: the numbers RESULTS.md gives for ycbv_real over seeds 0-7.
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections import defaultdict
from pathlib import Path


def summary(folder: Path) -> dict[str, dict]:
    """{NAME: {"seeds", "noicp", "icp", "f1", "ar": [per seed...], "objects": {name: ([noicp...], [icp...])}}}."""
    runs: dict[str, dict] = defaultdict(lambda: defaultdict(list))
    for report in sorted(folder.glob("*-*/report.json")):
        name, seed = report.parent.name.rsplit("-", 1)
        d = json.loads(report.read_text())
        r = runs[name]
        r["seeds"].append(int(seed))
        r["noicp"].append(100 * d["mean"]["noicp"]["0.10"])
        r["icp"].append(100 * d["mean"]["icp"]["0.10"])
        r["f1"].append(100 * d["f1"]["icp"]["f1"])
        r["ar"].append(d["bop19"].get("bop19_average_recall", float("nan")))
        for o in d["objects"]:
            r.setdefault("objects", defaultdict(lambda: ([], [])))
            r["objects"][o["name"]][0].append(100 * o["add"]["noicp"]["0.10"])
            r["objects"][o["name"]][1].append(100 * o["add"]["icp"]["0.10"])
    return runs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    folder = ap.parse_args().folder
    runs = summary(folder)
    if not runs:
        raise SystemExit(f"seeds.py: no NAME-SEED/report.json in {folder}")
    mean = statistics.mean
    print("| inference | seeds | w/o ICP | with ICP (range) | F1 with ICP | AR (range) | per object w/o / ICP |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for name, r in runs.items():
        objs = "; ".join(f"{o} {mean(a):.1f} / {mean(b):.1f}" for o, (a, b) in r["objects"].items())
        print(f"| {name} | {len(r['seeds'])} | {mean(r['noicp']):.1f} | {mean(r['icp']):.1f} ({min(r['icp']):.1f}-"
              f"{max(r['icp']):.1f}) | {mean(r['f1']):.1f} | {mean(r['ar']):.3f} ({min(r['ar']):.3f}-"
              f"{max(r['ar']):.3f}) | {objs} |")


if __name__ == "__main__":
    main()
