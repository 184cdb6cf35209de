"""The overtaking step (paper §IV-C): fine-tune the best source seed on the three-lane road
with slow SVs, then the fixed-seed tests; skipped while its test.json is still valid."""
from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Callable

import numpy as np

from bimacppo_common.conventions import OUTCOMES, TASKS

from .config import ExperimentConfig, ExperimentError
from .pool import Cluster, Job
from .runs import has_checkpoint, last_episode, read_eval_csv, read_history, run_status
from .traffic import draw_n_slow, make_overtake_env


def best_source_seed(cfg: ExperimentConfig) -> tuple[int, str]:
    """The source method's seed to fine-tune: best mean success of its cached training-map
    evaluation, else (nothing evaluated) best success over the last ``report.window`` training episodes."""
    o = cfg.overtake
    done = [s for s in cfg.seeds if run_status(cfg, o.source_method, s).done]
    if not done:
        raise ExperimentError(f"no finished {o.source_method} run under {Path(cfg.runs_dir) / cfg.train_map}: "
                              f"run `bimacppo-experiments train --only {o.source_method}` first")
    scores = {}
    for s in done:
        p = cfg.eval_prefix(cfg.run_dir(o.source_method, s), cfg.train_map).with_suffix(".csv")
        if p.is_file():
            scores[s] = float(np.mean([v[0] for v in read_eval_csv(p).values()]))
    if scores:
        s = max(scores, key=lambda k: (scores[k], -k))
        return s, f"best mean success on {cfg.train_map} evaluation ({scores[s]:.1f}%)"
    tail = {}
    for s in done:
        recs = read_history(cfg.run_dir(o.source_method, s))[-cfg.report.window:]
        tail[s] = float(np.mean([r["outcome"] == "success" for r in recs]))
    s = max(tail, key=lambda k: (tail[k], -k))
    return s, f"best training success over the last {cfg.report.window} episodes ({100 * tail[s]:.1f}%; not evaluated)"


def test_is_fresh(cfg: ExperimentConfig, out: Path) -> bool:
    """A cached test.json counts if it is newer than the fine-tuned policy and has the test size."""
    o, test_path, policy = cfg.overtake, out / "test.json", out / "policy.pt"
    if not (test_path.is_file() and policy.is_file()) or test_path.stat().st_mtime <= policy.stat().st_mtime:
        return False
    try:
        res = json.loads(test_path.read_text())
    except ValueError:
        return False
    return isinstance(res, dict) and res.get("episodes") == o.test_episodes and res.get("n_sv") == o.test_n_sv


def overtake_run(cfg: ExperimentConfig, source: str, seed: int, why: str, ckpt: str, out: str) -> str:
    """In the Ray worker: the fine-tune (unless it has its budget and policy) and the tests."""
    from bimacppo_planner.agent import env_config_of, load_policy

    o, out = cfg.overtake, Path(out)
    if last_episode(out) >= o.episodes and (out / "policy.pt").is_file():
        print(f"fine-tuned policy {out / 'policy.pt'} exists, not retrained", flush=True)
    else:
        print(f"fine-tuning {o.source_method}-s{seed} ({why}) from {ckpt}", flush=True)
        finetune(cfg, Path(ckpt), env_config_of(load_policy(Path(source) / "policy.pt")), out)
    res = overtake_test(cfg, out / "policy.pt")
    res.update(source=f"{o.source_method}-s{seed}", source_reason=why, init_checkpoint=str(ckpt))
    (out / "test.json").write_text(json.dumps(res, indent=2))
    return f"{res['success_pct']:.0f}% success over {res['episodes']} tests -> {out / 'test.json'}"


def overtake(cfg: ExperimentConfig, echo: Callable[[str], None] = print, cluster: Cluster | None = None) -> dict | None:
    """Fine-tune the best source seed on the overtaking road, then the fixed-seed tests, as one
    Ray task (``train.num_cpus`` CPUs; log ``<finetune dir>/overtake.log``). Returns the tests'
    result, None if the task failed (reported on one line)."""
    from ..checkpoint import latest_checkpoint

    o = cfg.overtake
    absolute = cfg.resolved()
    seed, why = best_source_seed(absolute)
    src = absolute.run_dir(o.source_method, seed)
    ckpt = latest_checkpoint(src / "checkpoints") if (src / "checkpoints").is_dir() else None
    if ckpt is None:
        raise ExperimentError(f"{src}: no training checkpoint in checkpoints/ to fine-tune from")
    out = absolute.overtake_dir(seed)
    if test_is_fresh(cfg, out):
        echo(f"overtaking: cached {out / 'test.json'}")
        return json.loads((out / "test.json").read_text())
    echo(f"overtaking: {o.source_method}-s{seed} ({why}), from {ckpt}")
    kwargs = {"cfg": absolute, "source": str(src), "seed": seed, "why": why, "ckpt": str(ckpt), "out": str(out)}
    own = cluster is None
    cluster = cluster or Cluster()
    try:
        [res] = cluster.run([Job("overtaking", overtake_run, kwargs, out / "overtake.log", cfg.train.num_cpus)],
                            "overtaking", echo, cfg.train.poll_s)
    finally:
        if own:
            cluster.close()
    return json.loads((out / "test.json").read_text()) if res.ok else None


def finetune(cfg: ExperimentConfig, ckpt: Path, env_cfg, out: Path) -> None:
    """bimacppo-train --init-policy with slow SVs, in-process (the same Trainer the CLI runs)."""
    from bimacppo_curriculum import make_scheduler

    from ..cli import run_meta
    from ..ppo_config import load_config
    from ..trainer import Trainer, load_agent

    o, t = cfg.overtake, cfg.train
    out.mkdir(parents=True, exist_ok=True)
    pcfg, tcfg = load_config(t.ppo_config, train={"seed": o.seed, "num_envs": t.num_envs, "vector": t.vector})
    sched = make_scheduler(o.curriculum, seed=o.seed, total_episodes=o.episodes)
    (out / "run.json").write_text(json.dumps({
        "curriculum": o.curriculum, "episodes": o.episodes, "seed": o.seed, "map": o.map, "mpc": t.mpc,
        "init_policy": str(ckpt), "n_slow_max": o.n_slow_max, "env_config": env_cfg.to_dict()}, indent=2))
    env_fn = make_overtake_env(o.map, env_cfg, t.mpc, o.n_slow_max)
    Trainer(env_fn, sched, out, pcfg, tcfg, agent=load_agent(ckpt),
            run_meta=run_meta(env_cfg, o.curriculum, o.map, o.seed, t.mpc)).train(o.episodes, resume=has_checkpoint(out))


def overtake_test(cfg: ExperimentConfig, policy_path: Path) -> dict:
    """``test_episodes`` episodes with ``test_n_sv`` SVs on the test seeds, the number of slow
    SVs drawn per seed (draw_n_slow): ``bimacppo-evaluate --map <map> --tasks <its task>
    --n-sv <test_n_sv> --slow-svs <n_slow_max>``, the same protocol."""
    from bimacppo_sim import load_map
    from ..evaluate import eval_seed, evaluate

    o = cfg.overtake
    road = load_map(o.map)
    j = TASKS.index(road.tasks[0])   # the road's first task, as the env picks it
    [cell] = evaluate(policy_path, o.map, (o.test_n_sv,), (j,), o.test_episodes, workers=1,
                      mpc_solver=cfg.train.mpc, random_row=False, seed_set="test", slow_svs=o.n_slow_max)
    slow = Counter(draw_n_slow(eval_seed(j, o.test_n_sv, k), o.test_n_sv, o.n_slow_max)
                   for k in range(o.test_episodes))
    n = o.test_episodes
    return {"episodes": n, "n_sv": o.test_n_sv, "n_slow_counts": {str(k): v for k, v in sorted(slow.items())},
            **{f"{x}_pct": 100.0 * cell.counts.get(x, 0) / n for x in OUTCOMES}}
