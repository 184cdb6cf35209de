"""The paper's evaluation protocol (§IV-B): every task x N_sv cell, fixed scenario seeds.

Every method is evaluated on exactly the same scenarios: the scenario seed of episode k
in cell (task j, N_sv i) is ``EVAL_SEED_BASE + 10_000*j + 1_000*i + k``, far away from
the seeds training draws (those come from the training RNG, uniformly in [0, 2^31)).
"""
from __future__ import annotations

import csv
import io
import multiprocessing as mp
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from bimacppo_sim import TASKS

EVAL_SEED_BASE = 1_000_000
OUTCOMES = ("success", "collision", "timeout")


def eval_seed(task: int, n_sv: int, k: int) -> int:
    if not (0 <= k < 1_000):
        raise ValueError(f"episode index {k} out of range: at most 1000 evaluation episodes per cell")
    return EVAL_SEED_BASE + 10_000 * task + 1_000 * n_sv + k


@dataclass
class CellResult:
    task: int
    n_sv: int
    counts: Counter
    returns: list

    @property
    def n(self) -> int:
        return sum(self.counts.values())

    def pct(self, outcome: str) -> float:
        return 100.0 * self.counts.get(outcome, 0) / max(self.n, 1)


def _run_cell(args):
    policy_path, map_id, task, n_sv, episodes, mpc_solver = args
    from bimacppo_planner.agent import env_config_of, load_policy
    from .env import IntersectionEnv

    policy = load_policy(policy_path)
    env = IntersectionEnv(map_id=map_id, config=env_config_of(policy), mpc_solver=mpc_solver)
    counts: Counter = Counter()
    returns = []
    for k in range(episodes):
        obs, _ = env.reset(options={"n_sv": n_sv, "task": task, "scenario_seed": eval_seed(task, n_sv, k)})
        done = False
        while not done:
            obs, _, term, trunc, info = env.step(policy.act(obs, deterministic=True))
            done = term or trunc
        counts[info["outcome"]] += 1
        returns.append(float(info["episode_return"]))
    return task, n_sv, counts, returns


def evaluate(policy_path: str, map_id: str = "dual_lane_4way", n_svs: Iterable[int] = (0, 1, 2, 3),
             tasks: Iterable[int] = (0, 1, 2), episodes: int = 100, workers: int = 2,
             mpc_solver: str = "fast", progress: Callable | None = None) -> list[CellResult]:
    """Run the protocol with a saved policy; cells are spread over ``workers`` processes."""
    jobs = [(str(policy_path), map_id, int(t), int(n), int(episodes), mpc_solver) for t in tasks for n in n_svs]
    results = []
    if workers <= 1:
        it = map(_run_cell, jobs)
        for r in it:
            results.append(CellResult(*r))
            if progress:
                progress(results[-1])
    else:
        ctx = mp.get_context("spawn")
        with ctx.Pool(workers) as pool:
            for r in pool.imap_unordered(_run_cell, jobs):
                results.append(CellResult(*r))
                if progress:
                    progress(results[-1])
    results.sort(key=lambda c: (c.task, c.n_sv))
    return results


def to_markdown(results: list[CellResult], title: str = "") -> str:
    """Table II layout: rows = task, column groups = N_sv, S / C / TO in percent."""
    n_svs = sorted({c.n_sv for c in results})
    by = {(c.task, c.n_sv): c for c in results}
    head = "| task | " + " | ".join(f"N_sv={n} S / C / TO (%)" for n in n_svs) + " |"
    sep = "|---|" + "---|" * len(n_svs)
    lines = ([f"**{title}**", ""] if title else []) + [head, sep]
    for t in sorted({c.task for c in results}):
        cells = []
        for n in n_svs:
            c = by.get((t, n))
            cells.append("–" if c is None else f"{c.pct('success'):.0f} / {c.pct('collision'):.0f} / {c.pct('timeout'):.0f}")
        lines.append(f"| {TASKS[t]} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def to_csv(results: list[CellResult]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["task", "n_sv", "episodes", "success_pct", "collision_pct", "timeout_pct", "mean_return"])
    for c in results:
        w.writerow([TASKS[c.task], c.n_sv, c.n, f"{c.pct('success'):.1f}", f"{c.pct('collision'):.1f}",
                    f"{c.pct('timeout'):.1f}", f"{np.mean(c.returns) if c.returns else float('nan'):.3f}"])
    return buf.getvalue()


def write_outputs(results: list[CellResult], out_prefix: str | Path, title: str = "") -> tuple[Path, Path]:
    out_prefix = Path(out_prefix)
    out_prefix.parent.mkdir(parents=True, exist_ok=True)
    md, cs = out_prefix.with_suffix(".md"), out_prefix.with_suffix(".csv")
    md.write_text(to_markdown(results, title))
    cs.write_text(to_csv(results))
    return md, cs
