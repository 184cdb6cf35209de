#!/usr/bin/env python3
"""Success over training seeds from `bimacppo-evaluate --out` CSVs: one row per file (mean over
its cells, and the N_sv = 3 cells), then each cell's mean ± sample std over the files.

    .venv/bin/python scripts/eval_summary.py runs/exp-batched2k/dual_lane_4way/bimab-s*/eval_dual.csv
"""
from __future__ import annotations

import argparse
import csv
import statistics
import sys

from bimacppo_common.conventions import TASKS



def read(path: str) -> dict[tuple[str, int], float]:
    with open(path, newline="") as fh:
        return {(r["task"], int(r["n_sv"])): float(r["success_pct"]) for r in csv.DictReader(fh)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", nargs="+")
    args = ap.parse_args()
    try:
        runs = [read(p) for p in args.csv]
    except (OSError, KeyError, ValueError) as exc:
        print(f"eval_summary: error: {exc}", file=sys.stderr)
        return 2
    cells = sorted(set().union(*runs), key=lambda c: (c[1], TASKS.index(c[0]) if c[0] in TASKS else 9))
    print("| file | mean success, all cells | N_sv = 3 left / straight / right |")
    print("|---|---|---|")
    means = []
    for p, r in zip(args.csv, runs):
        m = statistics.fmean(r.values())
        means.append(m)
        n3 = " / ".join(f"{r.get((t, 3), float('nan')):.0f}" for t in TASKS)
        print(f"| {p} | {m:.1f} | {n3} |")
    sd = statistics.stdev(means) if len(means) > 1 else float("nan")
    print(f"| mean ± std over {len(runs)} | {statistics.fmean(means):.1f} ± {sd:.1f} | |")
    print()
    print("| cell | success mean ± std over files |")
    print("|---|---|")
    for c in cells:
        v = [r[c] for r in runs if c in r]
        s = statistics.stdev(v) if len(v) > 1 else 0.0
        print(f"| {c[0]} N_sv={c[1]} | {statistics.fmean(v):.0f} ± {s:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
