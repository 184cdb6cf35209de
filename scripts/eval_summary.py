#!/usr/bin/env python3
"""Success over training seeds from `bimacppo-evaluate --out` CSVs: one row per file (mean over
its cells, and each task's success at every N_sv the files hold), each cell's mean ± sample std
over the files, and rliable's aggregates over files x cells: IQM and mean with stratified
bootstrap 95 % intervals, and, with ``--versus``, the probability that the first set improves on
the second.

    .venv/bin/python scripts/eval_summary.py runs/exp-batched2k/dual_lane_4way/bimab-s*/eval_dual.csv
    .venv/bin/python scripts/eval_summary.py runs/jr_s*/test_median.csv \\
        --versus runs/jr_s0/test_median_random.csv --names "BiM-ACPPO (13 + 14)" "random policy"
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


def aggregates(sets: dict[str, list[dict]], cells: list, reps: int) -> list[str]:
    """The rliable table of each named set of runs (rows of runs x cells)."""
    from bimacppo_learning.experiments.stats import improvement_probability, iqm_intervals, success_matrix

    mats = {name: success_matrix([{c: (r[c],) for c in cells if c in r} for r in runs], cells)
            for name, runs in sets.items()}
    est = iqm_intervals(mats, reps=reps)
    names = list(sets)
    lines = ["| set | runs | IQM [95 % CI] | mean [95 % CI] |"
             + (f" P({names[0]} > set) [95 % CI] |" if len(names) > 1 else ""),
             "|---|---|---|---|" + ("---|" if len(names) > 1 else "")]
    for name, e in est.items():
        row = (f"| {name} | {e['runs']} | {e['iqm']:.1f} [{e['iqm_ci'][0]:.1f}, {e['iqm_ci'][1]:.1f}] | "
               f"{e['mean']:.1f} [{e['mean_ci'][0]:.1f}, {e['mean_ci'][1]:.1f}] |")
        if len(names) > 1:
            if name == names[0]:
                row += " – |"
            else:
                p = improvement_probability(mats[names[0]], mats[name], reps=reps)
                row += f" {p['p']:.2f} [{p['ci'][0]:.2f}, {p['ci'][1]:.2f}] |"
        lines.append(row)
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", nargs="+", help="one evaluation CSV per training seed")
    ap.add_argument("--versus", nargs="*", default=[], help="CSVs of a second set (a baseline) to compare with")
    ap.add_argument("--names", nargs=2, default=("runs", "versus"), help="names of the two sets")
    ap.add_argument("--n-sv", type=int, nargs="*", default=None,
                    help="aggregate over these N_sv only (default: every cell of the files)")
    ap.add_argument("--reps", type=int, default=2000, help="bootstrap resamples (default 2000)")
    args = ap.parse_args(argv)
    try:
        runs = [read(p) for p in args.csv]
        versus = [read(p) for p in args.versus]
    except (OSError, KeyError, ValueError) as exc:
        print(f"eval_summary: error: {exc}", file=sys.stderr)
        return 2
    cells = sorted(set().union(*runs), key=lambda c: (c[1], TASKS.index(c[0]) if c[0] in TASKS else 9))
    n_svs = sorted({c[1] for c in cells})
    print("| file | mean success, all cells | " + " | ".join(f"N_sv = {n} left / straight / right" for n in n_svs) + " |")
    print("|---|---|" + "---|" * len(n_svs))
    means = []
    for p, r in zip(args.csv, runs):
        m = statistics.fmean(r.values())
        means.append(m)
        by_n = [" / ".join(f"{r.get((t, n), float('nan')):.0f}" for t in TASKS) for n in n_svs]
        print(f"| {p} | {m:.1f} | " + " | ".join(by_n) + " |")
    sd = statistics.stdev(means) if len(means) > 1 else float("nan")
    print(f"| mean ± std over {len(runs)} | {statistics.fmean(means):.1f} ± {sd:.1f} |" + " |" * len(n_svs))
    print()
    print("| cell | success mean ± std over files |")
    print("|---|---|")
    for c in cells:
        v = [r[c] for r in runs if c in r]
        s = statistics.stdev(v) if len(v) > 1 else 0.0
        print(f"| {c[0]} N_sv={c[1]} | {statistics.fmean(v):.0f} ± {s:.0f} |")
    chosen = [c for c in cells if args.n_sv is None or c[1] in args.n_sv]
    sets = {args.names[0]: runs}
    if versus:
        sets[args.names[1]] = versus
    try:
        table = aggregates(sets, chosen, args.reps)
    except ValueError as exc:
        print(f"eval_summary: error: {exc}", file=sys.stderr)
        return 2
    print()
    print(f"rliable over runs x {len(chosen)} cells (N_sv {sorted({c[1] for c in chosen})}), stratified "
          f"bootstrap, {args.reps} resamples:")
    print()
    print("\n".join(table))
    return 0


if __name__ == "__main__":
    sys.exit(main())
