"""Training report: figures and tables from one or more runs' ``history.jsonl``.

``bimacppo-report RUN_DIR [RUN_DIR ...] --out docs/img/NAME`` writes
- NAME_success.png: rolling success rate over training, overall and per N_sv (Fig.-style curves),
- NAME_fig5_clusters.png / NAME_fig6_arms.png: BiMAB cluster and arm weights (paper Figs. 5-6),
  for bandit curricula,
- NAME_table1.md: sampled counts per cluster and arm at the end of training (paper Table I),
and prints a short summary (episodes, wall-clock, episodes/s, final success rates).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def load_history(run_dir: str | Path) -> list[dict]:
    path = Path(run_dir) / "history.jsonl"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no history.jsonl (is {run_dir} a bimacppo-train run directory?)")
    recs = []
    for k, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            recs.append(json.loads(line))
        except json.JSONDecodeError:
            # a run killed mid-write leaves at most one partial last line: skip it, say so
            print(f"warning: {path}:{k}: unreadable line skipped", file=sys.stderr)
    if not recs:
        raise ValueError(f"{path}: no episodes recorded")
    return recs


def rolling_success(recs: list[dict], window: int = 200, n_sv: int | None = None):
    """(episode index, success rate over the last ``window`` matching episodes)."""
    sel = [(r["episode"], r["outcome"] == "success") for r in recs if n_sv is None or r["n_sv"] == n_sv]
    if not sel:
        return np.array([]), np.array([])
    ep = np.array([e for e, _ in sel], float)
    s = np.array([v for _, v in sel], float)
    c = np.cumsum(np.insert(s, 0, 0.0))
    lo = np.maximum(np.arange(1, len(s) + 1) - window, 0)
    rate = (c[1:] - c[lo]) / (np.arange(1, len(s) + 1) - lo)
    return ep, rate


def training_wall_s(recs: list[dict]) -> tuple[float, int]:
    """(training wall-clock over the whole run, number of segments). Each ``bimacppo-train``
    invocation (the first and every ``--resume``) restarts ``wall_s`` at 0, so a record whose
    ``wall_s`` is below its predecessor's starts a new segment and the run's time is the sum of
    each segment's last ``wall_s``. A resumed segment whose first episode took longer than the
    whole previous segment is not told apart (and its time is then undercounted). NaN if no
    record has ``wall_s``."""
    total, segments, last = 0.0, 0, None
    for r in recs:
        w = r.get("wall_s")
        if w is None:
            continue
        w = float(w)
        if last is None or w < last:
            if last is not None:
                total += last
            segments += 1
        last = w
    if last is None:
        return float("nan"), 0
    return total + last, segments


def summary(recs: list[dict]) -> dict:
    last = recs[-min(500, len(recs)):]
    by = {}
    for i in range(4):
        sub = [r for r in last if r["n_sv"] == i]
        if sub:
            by[i] = sum(r["outcome"] == "success" for r in sub) / len(sub)
    wall, segments = training_wall_s(recs)
    return {"episodes": recs[-1]["episode"], "env_steps": recs[-1].get("env_steps"), "wall_s": wall,
            "segments": segments,
            "episodes_per_s": recs[-1]["episode"] / wall if wall > 0 else float("nan"),
            "success_last_500_by_nsv": by}


def make_report(run_dirs: list[Path], out: Path, window: int = 200) -> dict:
    from bimacppo_curriculum import plots

    out.parent.mkdir(parents=True, exist_ok=True)
    runs = {Path(d).name: load_history(d) for d in run_dirs}
    written = []
    # success curves: overall per run, and per N_sv for the first run
    curves = {}
    for name, recs in runs.items():
        x, y = rolling_success(recs, window)
        curves[name] = (x, y, None)
    written.append(plots.plot_curves(curves, f"{out}_success.png", f"success rate (last {window} episodes)",
                                     "Training success rate"))
    first_name, first = next(iter(runs.items()))
    per = {}
    for i in range(4):
        x, y = rolling_success(first, max(1, window // 2), n_sv=i)
        if len(x):
            per[f"N_sv={i}"] = (x, y, None)
    written.append(plots.plot_curves(per, f"{out}_success_by_nsv.png",
                                     f"success rate (last {max(1, window // 2)} episodes of that N_sv)",
                                     f"{first_name}: success per N_sv"))
    hist = [dict(r["scheduler"], episodes=r["episode"]) for r in first]
    if "target_cluster_weight_0" in hist[0]:
        written.append(plots.plot_cluster_weights(hist, f"{out}_fig5_clusters.png",
                                                  f"{first_name}: BiMAB cluster weights (Fig. 5)"))
        if any(k.startswith("target_arm_weight_") for k in hist[0]):
            written.append(plots.plot_arm_weights(hist, f"{out}_fig6_arms.png",
                                                  f"{first_name}: BiMAB arm weights (Fig. 6)"))
    written.append(plots.plot_cluster_probabilities(hist, f"{out}_probs.png",
                                                    f"{first_name}: cluster sampling probabilities"))
    table = Path(f"{out}_table1.md")
    table.write_text(plots.counts_table_markdown(hist[-1]) + "\n")
    written.append(table)
    return {"files": [str(p) for p in written], "summary": {n: summary(r) for n, r in runs.items()}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="bimacppo-report", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path, help="bimacppo-train run directories")
    p.add_argument("--out", type=Path, required=True, help="output prefix, e.g. docs/img/bimab-s0")
    p.add_argument("--window", type=int, default=200, help="rolling window (episodes, >= 1)")
    args = p.parse_args(argv)
    from .cli import fail

    if args.window < 1:
        return fail(p.prog, f"--window must be >= 1 episode, got {args.window}")
    try:
        res = make_report(args.runs, args.out, args.window)
    except (OSError, ValueError, KeyError) as exc:
        return fail(p.prog, exc if not isinstance(exc, KeyError) else f"a history record lacks the key {exc}")
    for f in res["files"]:
        print("wrote", f)
    print(json.dumps(res["summary"], indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
