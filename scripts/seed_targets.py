#!/usr/bin/env python3
"""Which training runs meet the per-seed targets: for each run directory, its validation and test
success per task at N_sv = 3 and on the empty road (N_sv = 0), read from its `bimacppo-evaluate
--out` CSVs, and whether every N_sv = 3 cell reaches the threshold (default 95 %) and every
empty-road cell 100 %; then how many runs meet them on each seed set. A run missing a CSV shows
"-" and counts as not meeting the targets on that seed set.

    .venv/bin/python scripts/seed_targets.py runs/lr/s* --label "linear rates"
    .venv/bin/python scripts/seed_targets.py runs/b75/s* --versus runs/lr/s* --label "7,500" "5,000"
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bimacppo_common.conventions import TASKS
from bimacppo_learning.experiments import ExperimentError, read_eval_csv


def read_cells(path: Path) -> dict[tuple[int, int], float]:
    """(task index, N_sv) -> success % of one evaluation CSV (``experiments.read_eval_csv``, which
    names the file and row of a malformed one)."""
    return {cell: values[0] for cell, values in read_eval_csv(path).items()}


def meets(cells: dict | None, threshold: float) -> bool:
    """Every task at N_sv = 3 at or above ``threshold`` and every task at N_sv = 0 at 100 %."""
    if cells is None:
        return False
    return all(cells.get((t, 3), -1.0) >= threshold and cells.get((t, 0), -1.0) >= 100.0
               for t in range(len(TASKS)))


def _fmt(cells: dict | None, n_sv: int) -> str:
    if cells is None:
        return "-"
    return " / ".join("-" if (t, n_sv) not in cells else f"{cells[(t, n_sv)]:.0f}" for t in range(len(TASKS)))


def table(label: str, runs: list[Path], val_name: str, test_name: str, threshold: float) -> tuple[list[str], int, int]:
    """Markdown rows for ``runs`` and the counts of runs meeting the targets on validation / test."""
    rows, n_val, n_test = [], 0, 0
    for run in runs:
        v, t = (read_cells(run / f"{name}.csv") if (run / f"{name}.csv").is_file() else None
                for name in (val_name, test_name))
        v_ok, t_ok = meets(v, threshold), meets(t, threshold)
        n_val += v_ok
        n_test += t_ok
        rows.append(f"| {run.name} | {label} | {_fmt(v, 3)} | {_fmt(v, 0)} | {_fmt(t, 3)} | {_fmt(t, 0)} | "
                    f"{'yes' if v_ok else 'no'} | {'yes' if t_ok else 'no'} |")
    return rows, n_val, n_test


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="run directories holding the evaluation CSVs")
    ap.add_argument("--versus", nargs="*", type=Path, default=[], help="run directories of a second set")
    ap.add_argument("--label", nargs="+", default=["runs", "versus"], help="names of the set(s)")
    ap.add_argument("--validation", default="val_policy", help="validation CSV's name in each run (no .csv)")
    ap.add_argument("--test", default="test_policy", help="test CSV's name in each run (no .csv)")
    ap.add_argument("--threshold", type=float, default=95.0, help="per-cell N_sv = 3 target in %% (default 95)")
    args = ap.parse_args(argv)
    prog = "seed_targets.py"
    if not 0.0 <= args.threshold <= 100.0:
        print(f"{prog}: error: --threshold must be in 0..100, got {args.threshold}", file=sys.stderr)
        return 2
    missing = [str(r) for r in args.runs + args.versus if not r.is_dir()]
    if missing:
        print(f"{prog}: error: not a run directory: {', '.join(missing)}", file=sys.stderr)
        return 2
    labels = list(args.label) + ["versus"] * 2
    print("| run | set | validation N_sv = 3 L / S / R | validation N_sv = 0 | test N_sv = 3 L / S / R | "
          "test N_sv = 0 | targets met, validation | targets met, test |")
    print("|---|---|---|---|---|---|---|---|")
    counts = []
    try:
        for label, runs in ((labels[0], args.runs), (labels[1], args.versus)):
            if runs:
                rows, n_val, n_test = table(label, sorted(runs), args.validation, args.test, args.threshold)
                print("\n".join(rows))
                counts.append((label, len(runs), n_val, n_test))
    except ExperimentError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    print(f"\ntargets: >= {args.threshold:g} % in each N_sv = 3 cell and 100 % in each N_sv = 0 cell\n")
    print("| set | runs | targets met, validation seeds | targets met, test seeds |")
    print("|---|---|---|---|")
    for label, n, n_val, n_test in counts:
        print(f"| {label} | {n} | {n_val} of {n} | {n_test} of {n} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
