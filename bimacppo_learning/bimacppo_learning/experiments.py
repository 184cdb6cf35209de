"""``bimacppo-experiments``: the paper's experiment grid, from training to the results page.

Every method x seed is a ``bimacppo-train`` run in ``<runs_dir>/<map>/<method>-s<seed>``;
``evaluate`` caches each run's protocol CSVs next to it; ``overtake`` fine-tunes the best
BiM-ACPPO seed on the three-lane road; ``report`` turns whatever exists into
``docs/results_experiments.md`` and says what is missing instead of inventing numbers.
Each step skips what is already done, so ``all`` can be re-run after any interruption.
docs/experiments.md says how to run it and why each constant is what it is.
"""
from __future__ import annotations

import argparse
import csv
import functools
import json
import math
import os
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Callable, Mapping

import gymnasium as gym
import numpy as np
import yaml

from bimacppo_sim import TASKS

CONFIG_PATH = Path(__file__).resolve().parent / "config" / "experiments.yaml"
CURRICULA = ("bimab", "fixed", "random", "manual", "rd")
MAPS = ("dual_lane_4way", "single_lane_4way", "three_lane_straight")
DRIVERS = ("go", "yield")
METHOD_NAMES = {"bimab": "BiM-ACPPO", "fixed": "Fixed PPO", "random": "Random CPPO",
                "manual": "Manual CPPO", "rd": "RD-ACPPO", "go": 'scripted "go"', "yield": 'scripted "yield"'}
OUTCOMES = ("success", "collision", "timeout")


class ExperimentError(Exception):
    """A problem the user must fix (bad config, missing run, corrupt file): printed, exit code 2."""


# ----------------------------------------------------------------------------------------------
# configuration


def _int(lo=None, hi=None):
    def check(v):
        if isinstance(v, bool) or not isinstance(v, int):
            return f"must be an integer, got {v!r}"
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            return f"must be in {lo if lo is not None else '-inf'}..{hi if hi is not None else 'inf'}, got {v}"
        return None
    return check


def _float(lo, hi=None, lo_open=False):
    def check(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return f"must be a finite number, got {v!r}"
        if v < lo or (lo_open and v == lo) or (hi is not None and v > hi):
            return f"must be in {'(' if lo_open else '['}{lo}, {hi if hi is not None else 'inf'}], got {v}"
        return None
    return check


def _choice(options):
    def check(v):
        return None if v in options else f"must be one of {list(options)}, got {v!r}"
    return check


def _str(optional=False):
    def check(v):
        if v is None and optional:
            return None
        return None if isinstance(v, str) and v else f"must be a non-empty string{' or null' if optional else ''}, got {v!r}"
    return check


def _list(item, nonempty=True):
    def check(v):
        if not isinstance(v, list) or (nonempty and not v):
            return f"must be a {'non-empty ' if nonempty else ''}list, got {v!r}"
        if len(set(map(repr, v))) != len(v):
            return f"must not repeat items, got {v!r}"
        for x in v:
            err = item(x)
            if err:
                return f"item {x!r}: {err}"
        return None
    return check


@dataclass(frozen=True)
class TrainSection:
    num_envs: int
    vector: str
    mpc: str
    ppo_config: str | None
    poll_s: float
    env_config: str | None = None


@dataclass(frozen=True)
class EvalSection:
    episodes: int
    n_sv: tuple
    tasks: tuple
    workers: int
    reference_drivers: tuple


@dataclass(frozen=True)
class OvertakeSection:
    map: str
    source_method: str
    curriculum: str
    n_slow_max: int
    episodes: int
    seed: int
    test_episodes: int
    test_n_sv: int


@dataclass(frozen=True)
class ReportSection:
    window: int
    efficiency_fraction: float
    figure_seed: int


@dataclass(frozen=True)
class ExperimentConfig:
    methods: tuple
    seeds: tuple
    episodes: int
    train_map: str
    zero_shot_map: str | None
    runs_dir: str
    results_md: str
    img_prefix: str
    train: TrainSection
    evaluation: EvalSection
    overtake: OvertakeSection
    report: ReportSection
    source: str = "bimacppo_learning/config/experiments.yaml (packaged)"

    # -- layout: one place decides where everything lives ---------------------------------
    def run_dir(self, method: str, seed: int, map_id: str | None = None) -> Path:
        return Path(self.runs_dir) / (map_id or self.train_map) / f"{method}-s{seed}"

    def eval_prefix(self, run_dir: Path, map_id: str) -> Path:
        return run_dir / f"eval_{map_id}"

    def reference_prefix(self, driver: str, map_id: str) -> Path:
        return Path(self.runs_dir) / map_id / "reference" / driver

    def overtake_dir(self, source_seed: int) -> Path:
        o = self.overtake
        return Path(self.runs_dir) / o.map / f"{o.source_method}-s{source_seed}-finetune"

    def eval_maps(self) -> list[str]:
        return [self.train_map] + ([self.zero_shot_map] if self.zero_shot_map else [])


_SCHEMA: dict[str, Any] = {
    "methods": _list(_choice(CURRICULA)),
    "seeds": _list(_int(0)),
    "episodes": _int(1),
    "train_map": _choice(MAPS),
    "zero_shot_map": lambda v: None if v is None else _choice(MAPS)(v),
    "runs_dir": _str(),
    "results_md": _str(),
    "img_prefix": _str(),
    "train": {"num_envs": _int(1, 64), "vector": _choice(("async", "sync")), "mpc": _choice(("fast", "ipopt")),
              "ppo_config": _str(optional=True), "poll_s": _float(0.0, lo_open=True),
              "env_config": _str(optional=True)},
    "evaluation": {"episodes": _int(1, 1000), "n_sv": _list(_int(0, 3)), "tasks": _list(_choice(TASKS)),
                   "workers": _int(1, 64), "reference_drivers": _list(_choice(DRIVERS), nonempty=False)},
    "overtake": {"map": _choice(MAPS), "source_method": _choice(CURRICULA), "curriculum": _choice(CURRICULA),
                 "n_slow_max": _int(0, 3), "episodes": _int(1), "seed": _int(0), "test_episodes": _int(1, 1000),
                 "test_n_sv": _int(0, 3)},
    "report": {"window": _int(1), "efficiency_fraction": _float(0.0, 1.0, lo_open=True), "figure_seed": _int(0)},
}
_SECTIONS = {"train": TrainSection, "evaluation": EvalSection, "overtake": OvertakeSection, "report": ReportSection}


def _read_yaml(path: Path) -> dict:
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ExperimentError(f"{path}: cannot read experiments config: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise ExperimentError(f"{path}: not valid YAML: {exc}") from None
    doc = {} if doc is None else doc
    if not isinstance(doc, dict):
        raise ExperimentError(f"{path}: top level must be a mapping of keys")
    return doc


def load_experiment_config(path: str | os.PathLike | None = None, overrides: Mapping | None = None) -> ExperimentConfig:
    """The packaged experiments.yaml, with the keys of ``path`` (a YAML) and then ``overrides``
    (a dict) on top; every error names the file and the key (ValueError subclass not used:
    ExperimentError is what the CLI reports)."""
    base = _read_yaml(CONFIG_PATH)
    origin = {k: str(CONFIG_PATH) for k in base}
    layers = []
    if path is not None:
        layers.append((str(path), _read_yaml(Path(path))))
    if overrides:
        layers.append(("overrides", dict(overrides)))
    for src, doc in layers:
        for key, val in doc.items():
            if key not in _SCHEMA:
                raise ExperimentError(f"{src}: unknown key '{key}' (expected one of {sorted(_SCHEMA)})")
            if isinstance(_SCHEMA[key], dict):
                if not isinstance(val, dict):
                    raise ExperimentError(f"{src}: key '{key}' must be a mapping, got {val!r}")
                for sub in val:
                    if sub not in _SCHEMA[key]:
                        raise ExperimentError(f"{src}: unknown key '{key}.{sub}' "
                                              f"(expected one of {sorted(_SCHEMA[key])})")
                    origin[f"{key}.{sub}"] = src
                base[key] = {**(base.get(key) or {}), **val}
            else:
                base[key] = val
                origin[key] = src

    def value(key, sub=None):
        name = key if sub is None else f"{key}.{sub}"
        src = origin.get(name, origin.get(key, str(CONFIG_PATH)))
        sec = base.get(key) if sub is not None else base
        if not isinstance(sec, dict) or (sub or key) not in sec:
            raise ExperimentError(f"{src}: missing key '{name}'")
        v = sec[sub or key]
        check = _SCHEMA[key][sub] if sub is not None else _SCHEMA[key]
        err = check(v)
        if err:
            raise ExperimentError(f"{src}: key '{name}' {err}")
        return tuple(v) if isinstance(v, list) else v

    kw = {}
    for key, spec in _SCHEMA.items():
        if isinstance(spec, dict):
            cls = _SECTIONS[key]
            kw[key] = cls(**{f.name: value(key, f.name) for f in fields(cls)})
        else:
            kw[key] = value(key)
    if kw["zero_shot_map"] == "three_lane_straight" or kw["train_map"] == "three_lane_straight":
        raise ExperimentError(f"{origin.get('train_map')}: train_map / zero_shot_map must be intersections "
                              "(three_lane_straight is the overtaking map, see the 'overtake' section)")
    for name in ("ppo_config", "env_config"):
        f = getattr(kw["train"], name)
        if f is not None and not os.path.isfile(f):
            src = origin.get(f"train.{name}", origin.get("train", str(CONFIG_PATH)))
            raise ExperimentError(f"{src}: key 'train.{name}': no such file {f!r} (paths are relative to "
                                  f"the working directory, {os.getcwd()})")
    label = "bimacppo_learning/config/experiments.yaml (packaged)"
    return ExperimentConfig(**kw, source=f"{path} over {label}" if path is not None else label)


# ----------------------------------------------------------------------------------------------
# run state


def read_history(run_dir: str | os.PathLike) -> list[dict]:
    """All episode records of a run. A partial *last* line (a run killed mid-write) is dropped;
    anything else unreadable is a corrupt history, reported with file and line."""
    path = Path(run_dir) / "history.jsonl"
    if not path.is_file():
        raise ExperimentError(f"{path}: no history.jsonl (is {run_dir} a bimacppo-train run directory?)")
    lines = path.read_text().splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    recs: list[dict] = []
    for k, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            if k == len(lines):
                break
            raise ExperimentError(f"corrupt history {path}:{k}: not JSON") from None
        if not isinstance(rec, dict) or not isinstance(rec.get("episode"), int) or rec.get("outcome") not in OUTCOMES:
            raise ExperimentError(f"corrupt history {path}:{k}: a record needs an integer 'episode' and an "
                                  f"'outcome' in {OUTCOMES}")
        if recs and rec["episode"] != recs[-1]["episode"] + 1:
            raise ExperimentError(f"corrupt history {path}:{k}: episode {rec['episode']} follows "
                                  f"{recs[-1]['episode']}")
        recs.append(rec)
    return recs


def last_episode(run_dir: Path) -> int:
    """Episodes recorded so far, read from the end of history.jsonl (cheap: progress polling)."""
    path = Path(run_dir) / "history.jsonl"
    try:
        with path.open("rb") as fh:
            fh.seek(0, os.SEEK_END)
            fh.seek(max(0, fh.tell() - 65536))
            tail = fh.read().decode("utf-8", "replace").splitlines()
    except OSError:
        return 0
    for line in reversed(tail):
        try:
            return int(json.loads(line)["episode"])
        except (ValueError, KeyError, TypeError):
            continue
    return 0


@dataclass(frozen=True)
class RunStatus:
    method: str
    seed: int
    run_dir: Path
    episodes: int          # recorded in history.jsonl
    budget: int

    @property
    def done(self) -> bool:
        return self.episodes >= self.budget and (self.run_dir / "policy.pt").is_file()

    @property
    def state(self) -> str:
        if self.done:
            return "done"
        return "partial" if self.episodes or self.run_dir.exists() else "missing"


def run_status(cfg: ExperimentConfig, method: str, seed: int) -> RunStatus:
    d = cfg.run_dir(method, seed)
    return RunStatus(method, seed, d, last_episode(d), cfg.episodes)


def _has_checkpoint(run_dir: Path) -> bool:
    from .checkpoint import latest_checkpoint

    return (run_dir / "checkpoints").is_dir() and latest_checkpoint(run_dir / "checkpoints") is not None


def check_methods(methods) -> list[str]:
    bad = [m for m in methods if m not in CURRICULA]
    if bad:
        raise ExperimentError(f"unknown method(s) {bad}; expected some of {list(CURRICULA)}")
    return list(methods)


# ----------------------------------------------------------------------------------------------
# train


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
        resume = _has_checkpoint(j.run_dir)
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


# ----------------------------------------------------------------------------------------------
# evaluate


def read_eval_csv(path: str | os.PathLike) -> dict[tuple[int, int], tuple[float, float, float, int]]:
    """(task index, N_sv) -> (success %, collision %, timeout %, episodes) from an evaluation CSV."""
    path = Path(path)
    out = {}
    try:
        with path.open() as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise ExperimentError(f"{path}: cannot read evaluation CSV: {exc.strerror or exc}") from None
    for k, row in enumerate(rows, 2):
        try:
            key = (TASKS.index(row["task"]), int(row["n_sv"]))
            vals = (float(row["success_pct"]), float(row["collision_pct"]), float(row["timeout_pct"]),
                    int(row["episodes"]))
        except (KeyError, ValueError, TypeError) as exc:
            raise ExperimentError(f"{path}:{k}: malformed evaluation row ({type(exc).__name__}: {exc})") from None
        if not all(0.0 <= v <= 100.0 for v in vals[:3]):
            raise ExperimentError(f"{path}:{k}: percentages out of 0..100")
        out[key] = vals
    if not out:
        raise ExperimentError(f"{path}: no evaluation rows")
    return out


def _protocol_cells(cfg: ExperimentConfig) -> set[tuple[int, int]]:
    return {(TASKS.index(t), n) for t in cfg.evaluation.tasks for n in cfg.evaluation.n_sv}


def eval_is_fresh(cfg: ExperimentConfig, csv_path: Path, policy_path: Path | None) -> bool:
    """A cached CSV counts if it is newer than the policy and ran this config's protocol."""
    if not csv_path.is_file():
        return False
    if policy_path is not None and csv_path.stat().st_mtime <= policy_path.stat().st_mtime:
        return False
    try:
        cells = read_eval_csv(csv_path)
    except ExperimentError:
        return False
    return set(cells) == _protocol_cells(cfg) and all(v[3] == cfg.evaluation.episodes for v in cells.values())


def evaluate_reference(cfg: ExperimentConfig, driver: str, map_id: str, progress: Callable | None = None):
    """The scripted driver on exactly the policies' scenarios (same cells, same eval seeds)."""
    from bimacppo_sim import Scenario, World, load_map, run_episode

    from .evaluate import CellResult, eval_seed

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

    from .evaluate import evaluate, write_outputs

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


# ----------------------------------------------------------------------------------------------
# overtaking (paper §IV-C)


def _slow_rng(seed: int) -> np.random.Generator:
    """A stream of its own per scenario seed (a SeedSequence child), independent of the world's."""
    return np.random.default_rng(np.random.SeedSequence(int(seed)).spawn(1)[0])


def draw_n_slow(seed: int, n_sv: int, n_slow_max: int) -> int:
    """How many SVs drive slowly: uniform in 0..min(n_sv, n_slow_max), a function of the seed."""
    return int(_slow_rng(seed).integers(0, min(int(n_sv), n_slow_max) + 1))


class SlowTraffic(gym.Wrapper):
    """Overtaking episodes: the curriculum's task folds onto the road's only task, and each
    reset gets ``n_slow`` slow SVs (the env's reset option) drawn from the reset seed, because
    the trainer passes only ``n_sv`` and ``task``."""

    def __init__(self, env, n_slow_max: int):
        super().__init__(env)
        self.n_slow_max = int(n_slow_max)
        self._rng = np.random.default_rng()

    def reset(self, *, seed=None, options=None):
        from .env import task_index

        base = self.env.unwrapped
        opts = dict(options or {})
        if opts.get("task") is not None and len(base.tasks) == 1 and TASKS[task_index(opts["task"])] not in base.tasks:
            opts["task"] = base.tasks[0]
        if "n_slow" not in opts:
            rng = _slow_rng(seed) if seed is not None else self._rng
            if opts.get("n_sv") is None:
                opts["n_sv"] = int(rng.integers(0, base.max_sv + 1))
            opts["n_slow"] = int(rng.integers(0, min(int(opts["n_sv"]), self.n_slow_max) + 1))
        return self.env.reset(seed=seed, options=opts)


def make_overtake_env(map_id: str, env_config, mpc_solver: str, n_slow_max: int):
    """Picklable factory (async vector env workers) of the wrapped overtaking env."""
    from .env import IntersectionEnv

    return SlowTraffic(IntersectionEnv(map_id=map_id, config=env_config, mpc_solver=mpc_solver), n_slow_max)


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


def overtake(cfg: ExperimentConfig, echo: Callable[[str], None] = print) -> dict:
    """Fine-tune the best source seed on the overtaking road, then the fixed-seed tests."""
    from bimacppo_planner.agent import env_config_of, load_policy
    from .checkpoint import latest_checkpoint

    o = cfg.overtake
    seed, why = best_source_seed(cfg)
    src = cfg.run_dir(o.source_method, seed)
    ckpt = latest_checkpoint(src / "checkpoints") if (src / "checkpoints").is_dir() else None
    if ckpt is None:
        raise ExperimentError(f"{src}: no training checkpoint in checkpoints/ to fine-tune from")
    out = cfg.overtake_dir(seed)
    echo(f"overtaking: fine-tuning {o.source_method}-s{seed} ({why}) from {ckpt}")
    if last_episode(out) >= o.episodes and (out / "policy.pt").is_file():
        echo(f"overtaking: fine-tuned policy {out / 'policy.pt'} exists, skipped")
    else:
        _finetune(cfg, ckpt, env_config_of(load_policy(src / "policy.pt")), out)
    test_path = out / "test.json"
    policy = out / "policy.pt"
    if test_path.is_file() and test_path.stat().st_mtime > policy.stat().st_mtime:
        res = json.loads(test_path.read_text())
        if res.get("episodes") == o.test_episodes and res.get("n_sv") == o.test_n_sv:
            echo(f"overtaking: cached {test_path}")
            return res
    res = overtake_test(cfg, policy)
    res.update(source=f"{o.source_method}-s{seed}", source_reason=why, init_checkpoint=str(ckpt))
    test_path.write_text(json.dumps(res, indent=2))
    echo(f"overtaking: {res['success_pct']:.0f}% success over {res['episodes']} tests -> {test_path}")
    return res


def _finetune(cfg: ExperimentConfig, ckpt: Path, env_cfg, out: Path) -> None:
    """bimacppo-train --init-policy, in-process: the CLI cannot pass the wrapper that folds the
    tasks and sets n_slow (docs/experiments.md)."""
    from bimacppo_curriculum import make_scheduler

    from .cli import run_meta
    from .ppo_config import load_config
    from .trainer import Trainer, load_agent

    o, t = cfg.overtake, cfg.train
    out.mkdir(parents=True, exist_ok=True)
    pcfg, tcfg = load_config(t.ppo_config, train={"seed": o.seed, "num_envs": t.num_envs, "vector": t.vector})
    sched = make_scheduler(o.curriculum, seed=o.seed, total_episodes=o.episodes)
    (out / "run.json").write_text(json.dumps({
        "curriculum": o.curriculum, "episodes": o.episodes, "seed": o.seed, "map": o.map, "mpc": t.mpc,
        "init_policy": str(ckpt), "n_slow_max": o.n_slow_max, "env_config": env_cfg.to_dict()}, indent=2))
    env_fn = functools.partial(make_overtake_env, o.map, env_cfg, t.mpc, o.n_slow_max)
    Trainer(env_fn, sched, out, pcfg, tcfg, agent=load_agent(ckpt),
            run_meta=run_meta(env_cfg, o.curriculum, o.map, o.seed, t.mpc)).train(o.episodes, resume=_has_checkpoint(out))


def overtake_test(cfg: ExperimentConfig, policy_path: Path) -> dict:
    """``test_episodes`` episodes with ``test_n_sv`` SVs, seeds from evaluate.eval_seed, the
    number of slow SVs drawn per seed (draw_n_slow)."""
    from tqdm.auto import tqdm

    from bimacppo_planner.agent import env_config_of, load_policy
    from .evaluate import eval_seed

    o = cfg.overtake
    policy = load_policy(policy_path)
    env = make_overtake_env(o.map, env_config_of(policy), cfg.train.mpc, o.n_slow_max)
    task = env.unwrapped.tasks[0]
    j = TASKS.index(task)
    counts: Counter = Counter()
    slow: Counter = Counter()
    for k in tqdm(range(o.test_episodes), unit="ep", desc="overtaking tests", disable=None):
        seed = eval_seed(j, o.test_n_sv, k)
        n_slow = draw_n_slow(seed, o.test_n_sv, o.n_slow_max)
        slow[n_slow] += 1
        obs, _ = env.reset(options={"n_sv": o.test_n_sv, "task": task, "scenario_seed": seed, "n_slow": n_slow})
        done = False
        while not done:
            obs, _, term, trunc, info = env.step(policy.act(obs, deterministic=True))
            done = term or trunc
        counts[info["outcome"]] += 1
    env.close()
    n = o.test_episodes
    return {"episodes": n, "n_sv": o.test_n_sv, "n_slow_counts": {str(k): v for k, v in sorted(slow.items())},
            **{f"{x}_pct": 100.0 * counts[x] / n for x in OUTCOMES}}


# ----------------------------------------------------------------------------------------------
# aggregation (pure functions: tested on synthetic data)


def aggregate_cells(tables: list[Mapping]) -> dict[tuple[int, int], dict]:
    """Per cell, mean and sample standard deviation (ddof=1; NaN for one seed) of S/C/TO
    across the given evaluation tables; a cell counts only the tables that have it."""
    keys = sorted({k for t in tables for k in t})
    out = {}
    for key in keys:
        a = np.array([t[key][:3] for t in tables if key in t], float)
        std = a.std(axis=0, ddof=1) if len(a) > 1 else np.full(3, np.nan)
        out[key] = {"n": len(a), "mean": a.mean(axis=0), "std": std}
    return out


def rolling_rate(recs: list[dict], window: int) -> tuple[np.ndarray, np.ndarray]:
    """(episode, success rate over the last ``window`` episodes), only where a full window exists."""
    from .report import rolling_success

    x, y = rolling_success(recs, window)
    keep = x >= window
    return x[keep], y[keep]


def episodes_to_fraction(recs: list[dict], window: int, fraction: float) -> tuple[int | None, float]:
    """(first episode whose rolling success reaches ``fraction`` x the final one, final rate).
    Final = the rolling rate at the last episode. None when the run has no full window or its
    final rate is 0 (nothing to reach)."""
    x, y = rolling_rate(recs, window)
    if not len(x):
        return None, float("nan")
    final = float(y[-1])
    if final <= 0.0:
        return None, final
    hit = np.nonzero(y >= fraction * final - 1e-12)[0]
    return int(x[hit[0]]), final


def mean_std_curve(histories: list[list[dict]], window: int):
    """Rolling success of several seeds on their common episode range: (x, mean, std)."""
    curves = [rolling_rate(h, window) for h in histories]
    curves = [c for c in curves if len(c[0])]
    if not curves:
        return None
    hi = min(int(c[0][-1]) for c in curves)
    x = np.arange(window, hi + 1, dtype=float)
    ys = np.array([np.interp(x, cx, cy) for cx, cy in curves])
    return x, ys.mean(axis=0), ys.std(axis=0, ddof=1) if len(ys) > 1 else None


def mean_counts(logs: list[Mapping]) -> dict[str, float]:
    """Table I over seeds: mean of each count_i / count_i_j of the schedulers' final logs."""
    keys = sorted({k for lg in logs for k in lg if k.startswith("count_")})
    return {k: float(np.mean([lg.get(k, 0.0) for lg in logs])) for k in keys}


# ----------------------------------------------------------------------------------------------
# report


def _pm(mean: float, std: float) -> str:
    return f"{mean:.0f}" if not np.isfinite(std) else f"{mean:.0f}±{std:.0f}"


def table_markdown(rows: list[tuple[str, dict, int]], cfg: ExperimentConfig) -> str:
    """Table II/III layout: rows = method x task, columns = N_sv, cells S / C / TO (%) as
    mean±std over seeds (a single seed or a scripted driver: the value alone)."""
    nsv = list(cfg.evaluation.n_sv)
    lines = ["| method | task | " + " | ".join(f"N_sv={n} S / C / TO (%)" for n in nsv) + " | seeds |",
             "|---|---|" + "---|" * len(nsv) + "---|"]
    for name, agg, n_runs in rows:
        for t in cfg.evaluation.tasks:
            j = TASKS.index(t)
            cells = []
            for n in nsv:
                c = agg.get((j, n))
                cells.append("–" if c is None else " / ".join(_pm(c["mean"][k], c["std"][k]) for k in range(3)))
            lines.append(f"| {name} | {t} | " + " | ".join(cells) + f" | {n_runs or 'scripted'} |")
    return "\n".join(lines)


def counts_markdown(counts: Mapping[str, float]) -> str:
    n = 0
    while f"count_{n}" in counts:
        n += 1
    lines = ["| N_sv | sampled | " + " | ".join(f"{t} (j={j})" for j, t in enumerate(TASKS)) + " |",
             "|---:|---:|" + "---:|" * len(TASKS)]
    tot = np.zeros(len(TASKS))
    for i in range(n):
        arms = np.array([counts.get(f"count_{i}_{j}", 0.0) for j in range(len(TASKS))])
        tot += arms
        lines.append(f"| {i} | {counts[f'count_{i}']:.1f} | " + " | ".join(f"{a:.1f}" for a in arms) + " |")
    lines.append(f"| all | {tot.sum():.1f} | " + " | ".join(f"{a:.1f}" for a in tot) + " |")
    return "\n".join(lines)


def _img(cfg: ExperimentConfig, name: str) -> Path:
    return Path(f"{cfg.img_prefix}_{name}.png")


def _rel(path: Path, md: Path) -> str:
    return os.path.relpath(path, md.parent)


def report(cfg: ExperimentConfig, config_arg: str | None = None) -> dict:
    """Write the results page (+ PNGs) from whatever exists; returns {"path", "missing"}."""
    from bimacppo_curriculum import plots

    md_path = Path(cfg.results_md)
    md_path.parent.mkdir(parents=True, exist_ok=True)
    Path(cfg.img_prefix).parent.mkdir(parents=True, exist_ok=True)
    r = cfg.report
    missing: list[str] = []
    status = {(m, s): run_status(cfg, m, s) for m in cfg.methods for s in cfg.seeds}
    done = {k: v for k, v in status.items() if v.done}
    for (m, s), st in status.items():
        if not st.done:
            missing.append(f"training run `{m}-s{s}`: {st.state} ({st.episodes}/{cfg.episodes} episodes) "
                           f"in `{st.run_dir}`")
    hist = {k: read_history(v.run_dir) for k, v in done.items()}
    cfg_flag = f" --config {config_arg}" if config_arg else ""
    out = [f"# Experiment results (generated by `bimacppo-experiments{cfg_flag} report`)", "",
           f"Generated from the runs under `{cfg.runs_dir}` with the config `{cfg.source}`: "
           f"{len(cfg.methods)} methods x seeds {list(cfg.seeds)}, {cfg.episodes} training episodes each on "
           f"`{cfg.train_map}`, evaluation {cfg.evaluation.episodes} episodes per task x N_sv cell on the fixed "
           "seeds of `bimacppo_learning.evaluate.eval_seed` (shared by every method and by the scripted drivers). "
           "Numbers below are read from those files; nothing is typed in. Cells are S / C / TO in percent, "
           "mean±std (sample std, ddof=1) over the training seeds that finished and were evaluated.", "",
           "## Runs", "", "| method | " + " | ".join(f"seed {s}" for s in cfg.seeds) + " |",
           "|---|" + "---|" * len(cfg.seeds)]
    for m in cfg.methods:
        out.append(f"| {METHOD_NAMES[m]} | " + " | ".join(
            f"{status[(m, s)].state} ({status[(m, s)].episodes})" for s in cfg.seeds) + " |")
    # --- Tables II and III
    for title, map_id in (("Table II: success / collision / timeout on", cfg.train_map),
                          ("Table III: zero-shot on", cfg.zero_shot_map)):
        if map_id is None:
            continue
        rows = []
        for m in cfg.methods:
            tables = []
            for s in cfg.seeds:
                if (m, s) not in done:
                    continue
                p = cfg.eval_prefix(done[(m, s)].run_dir, map_id).with_suffix(".csv")
                if eval_is_fresh(cfg, p, done[(m, s)].run_dir / "policy.pt"):
                    tables.append(read_eval_csv(p))
                else:
                    missing.append(f"evaluation of `{m}-s{s}` on `{map_id}` (`{p}`)")
            if tables:
                rows.append((METHOD_NAMES[m], aggregate_cells(tables), len(tables)))
        for d in cfg.evaluation.reference_drivers:
            p = cfg.reference_prefix(d, map_id).with_suffix(".csv")
            if eval_is_fresh(cfg, p, None):
                rows.append((METHOD_NAMES[d], aggregate_cells([read_eval_csv(p)]), 0))
            else:
                missing.append(f"scripted driver `{d}` on `{map_id}` (`{p}`)")
        out += ["", f"## {title} `{map_id}`", ""]
        out.append(table_markdown(rows, cfg) if rows else "_no evaluated runs yet_")
        out.append("")
        out.append("`seeds` = training seeds averaged; scripted drivers are deterministic (one evaluation).")
    # --- Table I, Figs. 5-6
    bimab = [s for s in cfg.seeds if ("bimab", s) in done]
    out += ["", "## Table I: BiMAB sampled counts (mean over BiM-ACPPO seeds)", ""]
    if bimab:
        out.append(f"Mean over seeds {bimab} of the scheduler's final counts.")
        out += ["", counts_markdown(mean_counts([hist[("bimab", s)][-1]["scheduler"] for s in bimab]))]
        fs = r.figure_seed if r.figure_seed in bimab else bimab[0]
        h = [dict(rec["scheduler"], episodes=rec["episode"]) for rec in hist[("bimab", fs)]]
        f5 = plots.plot_cluster_weights(h, _img(cfg, "fig5_clusters"), f"BiM-ACPPO seed {fs}: cluster weights (Fig. 5)")
        f6 = plots.plot_arm_weights(h, _img(cfg, "fig6_arms"), f"BiM-ACPPO seed {fs}: arm weights (Fig. 6)")
        out += ["", f"## Figs. 5-6: BiMAB weights (BiM-ACPPO seed {fs})", "",
                f"![Fig. 5]({_rel(f5, md_path)})", "", f"![Fig. 6]({_rel(f6, md_path)})"]
    else:
        out.append("_no finished BiM-ACPPO run yet_")
    # --- success curves and sample efficiency
    curves, eff_rows = {}, []
    for m in cfg.methods:
        seeds = [s for s in cfg.seeds if (m, s) in done]
        if not seeds:
            continue
        c = mean_std_curve([hist[(m, s)] for s in seeds], r.window)
        if c is not None:
            curves[f"{METHOD_NAMES[m]} ({len(seeds)} seeds)"] = c
        per = [episodes_to_fraction(hist[(m, s)], r.window, r.efficiency_fraction) for s in seeds]
        reach = [e for e, _ in per if e is not None]
        finals = np.array([100 * f for _, f in per], float)
        fin = finals[np.isfinite(finals)]
        eff_rows.append(
            f"| {METHOD_NAMES[m]} | {len(seeds)} | "
            + (_pm(fin.mean(), fin.std(ddof=1) if len(fin) > 1 else np.nan) if len(fin) else "–") + " | "
            + (_pm(np.mean(reach), np.std(reach, ddof=1) if len(reach) > 1 else np.nan) if reach else "–") + " | "
            + ", ".join("–" if e is None else str(e) for e, _ in per) + " |")
    out += ["", "## Training success and sample efficiency", ""]
    if curves:
        f = plots.plot_curves(curves, _img(cfg, "success"), f"success rate (last {r.window} episodes)",
                              "Training success rate, mean ± std over seeds")
        out += [f"![success curves]({_rel(f, md_path)})", "",
                f"Rolling success over the last {r.window} training episodes (shown once a full window "
                "exists), mean over seeds with a ±1 std band, on the episodes every seed has.", "",
                f"Sample efficiency: the first episode at which a run's rolling success ({r.window}-episode "
                f"window) reaches {r.efficiency_fraction:.0%} of its own final rolling success (the value at "
                "its last episode); – = final success 0 or no full window.", "",
                f"| method | seeds | final success (%) | episodes to {r.efficiency_fraction:.0%} of final | per seed |",
                "|---|---|---|---|---|", *eff_rows]
    else:
        out.append("_no finished training run yet_")
    # --- overtaking
    o = cfg.overtake
    out += ["", f"## Overtaking on `{o.map}` (fine-tuned {METHOD_NAMES[o.source_method]}, paper §IV-C)", ""]
    tests = sorted(Path(cfg.runs_dir, o.map).glob(f"{o.source_method}-s*-finetune/test.json"))
    if tests:
        for tp in tests:
            t = json.loads(tp.read_text())
            out.append(f"- `{tp.parent.name}` (from {t.get('source')}, {t.get('source_reason', '')}): "
                       f"{t['episodes']} tests with {t['n_sv']} SVs (slow SVs per test: {t['n_slow_counts']}): "
                       f"success {t['success_pct']:.0f}%, collision {t['collision_pct']:.0f}%, "
                       f"timeout {t['timeout_pct']:.0f}%")
    else:
        out.append("_not run yet_")
        missing.append(f"overtaking fine-tune + tests (`{Path(cfg.runs_dir, o.map)}`)")
    # --- commands and missing
    c = f"bimacppo-experiments{cfg_flag}"
    out += ["", "## Commands", "", "```bash",
            f"{c} all          # everything below, skipping what is done",
            f"{c} train        # each run = bimacppo-train " + " ".join(train_argv(cfg, "<method>", "<seed>", False)),
            f"{c} evaluate     # bimacppo-evaluate protocol per run on {', '.join(cfg.eval_maps())} + scripted drivers",
            f"{c} overtake     # fine-tune the best {o.source_method} seed on {o.map}, {o.episodes} episodes; {o.test_episodes} tests",
            f"{c} report       # this page", "```", "", "## Missing", ""]
    out += [f"- {x}" for x in missing] if missing else ["Nothing: every run, evaluation and test exists."]
    md_path.write_text("\n".join(out) + "\n")
    return {"path": str(md_path), "missing": missing}


# ----------------------------------------------------------------------------------------------
# CLI


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bimacppo-experiments", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=None, help="YAML with the keys of config/experiments.yaml to change")
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train every missing run (resume unfinished ones), one at a time")
    t.add_argument("--only", nargs="+", metavar="METHOD", help=f"methods among {list(CURRICULA)}")
    t.add_argument("--seeds", nargs="+", type=int, help="seeds (default: the config's)")
    sub.add_parser("evaluate", help="paper protocol for every finished run (training + zero-shot map) and the scripted drivers")
    sub.add_parser("overtake", help="fine-tune the best BiM-ACPPO seed on the 3-lane road, then the tests")
    sub.add_parser("report", help="write the results page and figures from what exists")
    sub.add_parser("all", help="train -> evaluate -> overtake -> report")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = load_experiment_config(args.config)
        rc = 0
        if args.cmd in ("train", "all"):
            rc |= int(train(cfg, getattr(args, "only", None), getattr(args, "seeds", None)) > 0)
        if args.cmd in ("evaluate", "all"):
            evaluate_all(cfg)
        if args.cmd in ("overtake", "all"):
            try:
                overtake(cfg)
            except ExperimentError as exc:
                if args.cmd == "overtake":
                    raise
                print(f"overtaking skipped: {exc}")
        if args.cmd in ("report", "all"):
            res = report(cfg, args.config)
            print(f"wrote {res['path']} ({len(res['missing'])} item(s) missing)")
        return rc
    except ExperimentError as exc:
        print(f"bimacppo-experiments: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
