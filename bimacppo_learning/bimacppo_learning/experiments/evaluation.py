"""The evaluation step: the paper's protocol for every finished run on the training and
zero-shot maps, and the scripted drivers on the same scenarios; valid cached CSVs are kept."""
from __future__ import annotations

from collections import Counter
from typing import Callable

from bimacppo_sim import TASKS

from .config import METHOD_NAMES, ExperimentConfig, ExperimentError
from .runs import eval_is_fresh, run_status


def evaluate_reference(cfg: ExperimentConfig, driver: str, map_id: str, progress: Callable | None = None):
    """The scripted driver on exactly the policies' scenarios (same cells, same eval seeds)."""
    from bimacppo_sim import Scenario, World, load_map, run_episode

    from ..evaluate import CellResult, eval_seed

    road = load_map(map_id)
    world = World(road)
    results = []
    for t in cfg.evaluation.tasks:
        j = TASKS.index(t)
        for n in cfg.evaluation.n_sv:
            if t not in road.turns or n > road.max_sv:
                raise ExperimentError(f"map {map_id!r} has no cell task={t} N_sv={n}; fix evaluation.tasks/n_sv")
            counts: Counter = Counter()
            for k in range(cfg.evaluation.episodes):
                counts[run_episode(world, Scenario(n, t, eval_seed(j, n, k)), driver).outcome] += 1
            results.append(CellResult(j, n, counts, []))
            if progress:
                progress(results[-1])
    return results


def evaluate_all(cfg: ExperimentConfig, echo: Callable[[str], None] = print) -> list[str]:
    """The protocol for every finished run on the training and zero-shot maps, plus the scripted
    drivers; cached CSVs that are still valid are kept. Returns the runs that are not finished."""
    from tqdm.auto import tqdm

    from ..evaluate import evaluate, write_outputs

    e = cfg.evaluation
    tasks = [TASKS.index(t) for t in e.tasks]
    n_cells = len(tasks) * len(e.n_sv)
    missing = []
    for m in cfg.methods:
        for s in cfg.seeds:
            st = run_status(cfg, m, s)
            if not st.done:
                missing.append(f"{m}-s{s} ({st.state}, {st.episodes}/{cfg.episodes} episodes)")
                continue
            policy = st.run_dir / "policy.pt"
            for map_id in cfg.eval_maps():
                prefix = cfg.eval_prefix(st.run_dir, map_id)
                if eval_is_fresh(cfg, prefix.with_suffix(".csv"), policy):
                    echo(f"{m}-s{s} on {map_id}: cached {prefix.with_suffix('.csv')}")
                    continue
                bar = tqdm(total=n_cells, unit="cell", desc=f"{m}-s{s} {map_id}", disable=None)
                res = evaluate(policy, map_id, e.n_sv, tasks, e.episodes, e.workers, cfg.train.mpc,
                               lambda c: bar.update(1))
                bar.close()
                md, cs = write_outputs(res, prefix, f"{METHOD_NAMES[m]} seed {s} on {map_id}")
                echo(f"{m}-s{s} on {map_id}: wrote {cs}")
    for map_id in cfg.eval_maps():
        for d in e.reference_drivers:
            prefix = cfg.reference_prefix(d, map_id)
            if eval_is_fresh(cfg, prefix.with_suffix(".csv"), None):
                echo(f"{d} on {map_id}: cached {prefix.with_suffix('.csv')}")
                continue
            bar = tqdm(total=n_cells, unit="cell", desc=f"{d} {map_id}", disable=None)
            res = evaluate_reference(cfg, d, map_id, lambda c: bar.update(1))
            bar.close()
            md, cs = write_outputs(res, prefix, f"{METHOD_NAMES[d]} on {map_id}")
            echo(f"{d} on {map_id}: wrote {cs}")
    if missing:
        echo("not evaluated (not finished): " + ", ".join(missing))
    return missing
