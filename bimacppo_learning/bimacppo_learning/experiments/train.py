"""The training step: every method x seed of the grid as a ``bimacppo-train`` run."""
from __future__ import annotations

import subprocess
import sys
import time
from typing import Callable

from .config import ExperimentConfig, ExperimentError, check_methods
from .runs import has_checkpoint, last_episode, read_history, run_status


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


def train(cfg: ExperimentConfig, only=None, seeds=None, echo: Callable[[str], None] | None = None) -> int:
    """Train every missing run in sequence (each in its own ``bimacppo-train`` process, log in
    ``<run>/train.log``); unfinished runs with a checkpoint resume. Returns the number of failures."""
    from tqdm.auto import tqdm

    methods = check_methods(only) if only else list(cfg.methods)
    seeds = list(seeds) if seeds else list(cfg.seeds)
    if any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in seeds):
        raise ExperimentError(f"seeds must be integers >= 0, got {seeds}")
    jobs = [run_status(cfg, m, s) for m in methods for s in seeds]
    todo = [j for j in jobs if not j.done]
    bar = tqdm(total=sum(cfg.episodes - min(j.episodes, cfg.episodes) for j in todo), unit="ep", desc="training",
               disable=None)
    say = echo or bar.write
    failures = 0
    for j in jobs:
        name = f"{j.method}-s{j.seed}"
        if j.done:
            say(f"{name}: done ({j.episodes} episodes), skipped")
            continue
        resume = has_checkpoint(j.run_dir)
        j.run_dir.mkdir(parents=True, exist_ok=True)
        argv = train_argv(cfg, j.method, j.seed, resume)
        log = j.run_dir / "train.log"
        t0, seen = time.monotonic(), j.episodes
        with log.open("a") as fh:
            fh.write(f"$ bimacppo-train {' '.join(argv)}\n")
            fh.flush()
            proc = subprocess.Popen([sys.executable, "-m", "bimacppo_learning.cli", *argv], stdout=fh,
                                    stderr=subprocess.STDOUT)
            try:
                while proc.poll() is None:
                    time.sleep(cfg.train.poll_s)
                    now = min(last_episode(j.run_dir), cfg.episodes)
                    if now > seen:
                        bar.update(now - seen)
                        seen = now
            except KeyboardInterrupt:
                proc.terminate()
                proc.wait()
                raise
        now = run_status(cfg, j.method, j.seed)
        bar.update(max(0, min(now.episodes, cfg.episodes) - seen))
        if proc.returncode != 0 or not now.done:
            failures += 1
            say(f"{name}: FAILED (exit {proc.returncode}, {now.episodes}/{cfg.episodes} episodes); see {log}")
            continue
        recs = read_history(j.run_dir)
        tail = recs[-min(cfg.report.window, len(recs)):]
        sr = 100.0 * sum(r["outcome"] == "success" for r in tail) / len(tail)
        say(f"{name}: {'resumed' if resume else 'trained'} to {now.episodes} episodes in "
            f"{time.monotonic() - t0:.0f} s; success over the last {len(tail)}: {sr:.0f}% -> {j.run_dir}")
    bar.close()
    return failures
