"""The evaluation step: the paper's protocol for every finished run on the training and
zero-shot maps, and the scripted drivers on the same scenarios. Each (policy, map) and each
(driver, map) is one Ray task (``evaluation.num_cpus`` CPUs; inside it ``evaluation.workers``
processes share the cells); a cached CSV that is still valid (runs.eval_is_fresh) is kept."""
from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Callable

from bimacppo_common.conventions import TASKS

from .config import METHOD_NAMES, ExperimentConfig, ExperimentError
from .pool import Cluster, Job
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


def evaluate_policy_run(cfg: ExperimentConfig, policy: str, map_id: str, prefix: str, title: str) -> str:
    """One policy on one map, in the Ray worker: writes ``prefix``.md/.csv."""
    from ..evaluate import evaluate, write_outputs

    e = cfg.evaluation
    print(f"evaluating {policy} on {map_id}: {e.episodes} episodes x tasks {list(e.tasks)} x N_sv {list(e.n_sv)}",
          flush=True)
    res = evaluate(policy, map_id, e.n_sv, [TASKS.index(t) for t in e.tasks], e.episodes, e.workers, cfg.train.mpc)
    _, cs = write_outputs(res, prefix, title)
    return f"wrote {cs}"


def evaluate_driver_run(cfg: ExperimentConfig, driver: str, map_id: str, prefix: str, title: str) -> str:
    """One scripted driver on one map, in the Ray worker."""
    from ..evaluate import write_outputs

    _, cs = write_outputs(evaluate_reference(cfg, driver, map_id), prefix, title)
    return f"wrote {cs}"


def evaluate_all(cfg: ExperimentConfig, echo: Callable[[str], None] = print, cluster: Cluster | None = None) -> int:
    """Evaluate what needs it; runs that are not finished are listed. Logs:
    ``<prefix>.log`` next to each CSV. Returns the number of failed evaluations."""
    absolute = cfg.resolved()
    jobs, missing = [], []
    for m in cfg.methods:
        for s in cfg.seeds:
            st = run_status(absolute, m, s)
            if not st.done:
                missing.append(f"{m}-s{s} ({st.state}, {st.episodes}/{cfg.episodes} episodes)")
                continue
            policy = st.run_dir / "policy.pt"
            for map_id in cfg.eval_maps():
                prefix = absolute.eval_prefix(st.run_dir, map_id)
                if eval_is_fresh(cfg, prefix.with_suffix(".csv"), policy):
                    echo(f"{m}-s{s} on {map_id}: cached {prefix.with_suffix('.csv')}")
                    continue
                kwargs = {"cfg": absolute, "policy": str(policy), "map_id": map_id, "prefix": str(prefix),
                          "title": f"{METHOD_NAMES[m]} seed {s} on {map_id}"}
                jobs.append(Job(f"{m}-s{s} on {map_id}", evaluate_policy_run, kwargs,
                                Path(f"{prefix}.log"), cfg.evaluation.num_cpus))
    for map_id in cfg.eval_maps():
        for d in cfg.evaluation.reference_drivers:
            prefix = absolute.reference_prefix(d, map_id)
            if eval_is_fresh(cfg, prefix.with_suffix(".csv"), None):
                echo(f"{d} on {map_id}: cached {prefix.with_suffix('.csv')}")
                continue
            kwargs = {"cfg": absolute, "driver": d, "map_id": map_id, "prefix": str(prefix),
                      "title": f"{METHOD_NAMES[d]} on {map_id}"}
            jobs.append(Job(f"{d} on {map_id}", evaluate_driver_run, kwargs, Path(f"{prefix}.log"),
                            cfg.evaluation.num_cpus))
    own = cluster is None
    cluster = cluster or Cluster()
    try:
        outcomes = cluster.run(jobs, "evaluation", echo, cfg.train.poll_s)
    finally:
        if own:
            cluster.close()
    if missing:
        echo("not evaluated (not finished): " + ", ".join(missing))
    return sum(not o.ok for o in outcomes)
