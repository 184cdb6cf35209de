"""The training step: every method x seed of the grid is a ``bimacppo-train`` run, one Ray task
each (``train.num_cpus`` CPUs), called in-process in the worker (``cli.train_main``).

Finished runs with this config's settings are skipped; an unfinished one resumes from its
latest checkpoint (decided in the worker, so a task that Ray reruns after a lost worker
resumes too); a run directory holding a run with other settings fails without being touched.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from .config import ExperimentConfig, ExperimentError, check_methods
from .pool import Cluster, Job, RunFailed
from .runs import has_checkpoint, last_episode, read_history, run_settings, run_status, write_settings


def train_argv(cfg: ExperimentConfig, method: str, seed: int, resume: bool) -> list[str]:
    """The exact ``bimacppo-train`` arguments of one run (also printed in the report)."""
    t = cfg.train
    argv = ["--curriculum", method, "--episodes", str(cfg.episodes), "--seed", str(seed),
            "--map", cfg.train_map, "--run-dir", str(cfg.run_dir(method, seed)),
            "--num-envs", str(t.num_envs), "--vector", t.vector, "--mpc", t.mpc, "--no-progress"]
    if t.ppo_config:
        argv += ["--ppo-config", t.ppo_config]
    if t.env_config:
        argv += ["--env-config", t.env_config]
    return argv + (["--resume"] if resume else [])


def last_line(path: Path) -> str:
    try:
        lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1] if lines else ""


def train_run(argv: list[str], run_dir: str, log: str, budget: int, window: int, settings: dict) -> str:
    """One training run, in the Ray worker: ``bimacppo-train ARGV [--resume]``; raises RunFailed
    unless the run reaches its budget with a policy."""
    from ..cli import train_main

    d = Path(run_dir)
    resume = has_checkpoint(d)
    argv = list(argv) + (["--resume"] if resume else [])
    write_settings(d, settings)
    print(f"$ bimacppo-train {' '.join(argv)}", flush=True)
    t0 = time.monotonic()
    rc = train_main(argv)
    n = last_episode(d)
    if rc != 0:
        raise RunFailed(f"bimacppo-train exited {rc}: {last_line(Path(log))}")
    if n < budget or not (d / "policy.pt").is_file():
        raise RunFailed(f"bimacppo-train ended at {n}/{budget} episodes without a policy.pt")
    recs = read_history(d)
    tail = recs[-min(window, len(recs)):]
    sr = 100.0 * sum(r["outcome"] == "success" for r in tail) / len(tail)
    return (f"{'resumed' if resume else 'trained'} to {n} episodes in {time.monotonic() - t0:.0f} s; "
            f"success over the last {len(tail)}: {sr:.0f}% -> {d}")


def train(cfg: ExperimentConfig, only=None, seeds=None, echo: Callable[[str], None] | None = None,
          cluster: Cluster | None = None) -> int:
    """Train every run that is not done, as Ray tasks on ``cluster`` (default: a local Ray for
    this call). Log per run: ``<run>/train.log``. Returns the number of failed runs."""
    methods = check_methods(only) if only else list(cfg.methods)
    seeds = list(seeds) if seeds else list(cfg.seeds)
    if any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in seeds):
        raise ExperimentError(f"seeds must be integers >= 0, got {seeds}")
    say = echo or print
    absolute = cfg.resolved()
    jobs, failures = [], 0
    for m in methods:
        for s in seeds:
            st = run_status(absolute, m, s)
            name, log = f"{m}-s{s}", st.run_dir / "train.log"
            if st.mismatch:
                failures += 1
                say(f"{name}: FAILED: {st.run_dir} holds a run with other settings ({', '.join(st.mismatch)} "
                    f"differ from the config); move it away or change runs_dir (log: {log})")
            elif st.done:
                say(f"{name}: done ({st.episodes} episodes), skipped")
            else:
                kwargs = {"argv": train_argv(absolute, m, s, resume=False), "run_dir": str(st.run_dir),
                          "log": str(log), "budget": cfg.episodes, "window": cfg.report.window,
                          "settings": run_settings(absolute, m, s)}
                jobs.append(Job(name, train_run, kwargs, log, cfg.train.num_cpus))
    own = cluster is None
    cluster = cluster or Cluster()
    try:
        outcomes = cluster.run(jobs, "training", echo, cfg.train.poll_s)
    finally:
        if own:
            cluster.close()
    return failures + sum(not o.ok for o in outcomes)
