"""The experiments config: experiments.yaml read through bimacppo_common.config into frozen
dataclasses, and the layout of every output path.

The packaged experiments.yaml is the only place a default is written (``ExperimentConfig()`` is
the paper's grid); a ``--config`` file lists only the keys it changes and is deep-merged onto it
(sections key by key). Every value is checked where it is declared (``setting``) or, for rules
over several keys, in ``_check``; an error is a ``ConfigError`` naming the file that set the key
and the dotted key, with the closest known key suggested for an unknown one.

Paths (``runs_dir``, ``results_md``, ``img_prefix``, ``train.ppo_config``, ``train.env_config``)
are relative to the working directory, not to the config file: the grid is run from the
repository root, and ``resolved()`` makes them absolute for the Ray tasks.
"""
from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Mapping

from bimacppo_common import config
from bimacppo_common.config import Packaged, config_class, invalid, runtime, setting
from bimacppo_common.conventions import TASKS

from ..ppo_config import VECTOR_MODES

EXPERIMENTS_YAML = Packaged("bimacppo_learning", "config/experiments.yaml")
CONFIG_PATH = Path(EXPERIMENTS_YAML.path)
PACKAGED_LABEL = "bimacppo_learning/config/experiments.yaml (packaged)"
CURRICULA = ("bimab", "fixed", "random", "manual", "rd")
MAPS = ("dual_lane_4way", "single_lane_4way", "three_lane_straight")
DRIVERS = ("go", "yield")
METHOD_NAMES = {"bimab": "BiM-ACPPO", "fixed": "Fixed PPO", "random": "Random CPPO",
                "manual": "Manual CPPO", "rd": "RD-ACPPO", "go": 'scripted "go"', "yield": 'scripted "yield"'}
_N_SV = dict(lo=0, hi=3)
_CPUS = dict(lo=1, hi=256)


class ExperimentError(Exception):
    """A problem the user must fix (missing run, corrupt file, bad method name): printed, exit
    code 2. A bad config is a ``ConfigError``, reported the same way."""


def _no_repeats(obj, *names: str) -> None:
    """A grid lists each method, seed, N_sv, task and driver once: a repeat would run or count
    the same cell twice."""
    for name in names:
        values = getattr(obj, name)
        if len(set(values)) != len(values):
            raise invalid(name, f"must not repeat items, got {list(values)!r}")


def _non_empty(obj, *names: str) -> None:
    for name in names:
        if getattr(obj, name) == "":
            raise invalid(name, "must be a non-empty string" + (" or null" if name.endswith("_config") else ""))


@config_class(EXPERIMENTS_YAML, "train")
class TrainSection:
    """How each training run is launched (one ``bimacppo-train`` Ray task per method x seed)."""

    num_envs: int = setting(lo=1, hi=64)
    vector: str = setting(choices=VECTOR_MODES)
    mpc: str = setting(choices=("fast", "ipopt"))
    ppo_config: str | None
    poll_s: float = setting(lo=0.0, lo_open=True)
    env_config: str | None
    num_cpus: int = setting(**_CPUS)

    def _check(self) -> None:
        _non_empty(self, "ppo_config", "env_config")
        for name in ("ppo_config", "env_config"):
            f = getattr(self, name)
            if f is not None and not os.path.isfile(f):
                raise invalid(name, f"no such file {f!r} (paths are relative to the working directory, "
                                    f"{os.getcwd()})")


@config_class(EXPERIMENTS_YAML, "evaluation")
class EvalSection:
    """The evaluation protocol (cells task x N_sv) and the scripted drivers compared with."""

    episodes: int = setting(lo=1, hi=1000)
    n_sv: tuple[int, ...] = setting(**_N_SV, min_length=1)
    tasks: tuple[str, ...] = setting(choices=TASKS, min_length=1)
    workers: int = setting(lo=1, hi=64)
    reference_drivers: tuple[str, ...] = setting(choices=DRIVERS)
    num_cpus: int = setting(**_CPUS)

    def _check(self) -> None:
        _no_repeats(self, "n_sv", "tasks", "reference_drivers")


@config_class(EXPERIMENTS_YAML, "overtake")
class OvertakeSection:
    """Fine-tuning the best source run on the three-lane road, and its tests."""

    map: str = setting(choices=MAPS)
    source_method: str = setting(choices=CURRICULA)
    curriculum: str = setting(choices=CURRICULA)
    n_slow_max: int = setting(**_N_SV)
    episodes: int = setting(lo=1)
    seed: int = setting(lo=0)
    test_episodes: int = setting(lo=1, hi=1000)
    test_n_sv: int = setting(**_N_SV)


@config_class(EXPERIMENTS_YAML, "report")
class ReportSection:
    """Constants of the results page and its figures."""

    window: int = setting(lo=1)
    efficiency_fraction: float = setting(lo=0.0, hi=1.0, lo_open=True)
    figure_seed: int = setting(lo=0)
    bootstrap_reps: int = setting(lo=100, hi=1_000_000)


@config_class(EXPERIMENTS_YAML)
class ExperimentConfig:
    """The whole grid: experiments.yaml's layout, plus where every output lives."""

    methods: tuple[str, ...] = setting(choices=CURRICULA, min_length=1)
    seeds: tuple[int, ...] = setting(lo=0, min_length=1)
    episodes: int = setting(lo=1)
    train_map: str = setting(choices=MAPS)
    zero_shot_map: str | None = setting(choices=MAPS)
    runs_dir: str
    results_md: str
    img_prefix: str
    train: TrainSection
    evaluation: EvalSection
    overtake: OvertakeSection
    report: ReportSection
    source: str = runtime(PACKAGED_LABEL)   # what the results page says it was generated from

    def _check(self) -> None:
        _no_repeats(self, "methods", "seeds")
        _non_empty(self, "runs_dir", "results_md", "img_prefix")
        for name in ("train_map", "zero_shot_map"):
            if getattr(self, name) == "three_lane_straight":
                raise invalid(name, "must be an intersection (three_lane_straight is the overtaking map, "
                                    "see the 'overtake' section)")

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

    def resolved(self) -> "ExperimentConfig":
        """The same config with absolute paths: what the Ray tasks get, since a worker (on
        another node, or a process that changed directory) must find the same files."""
        def absolute(p):
            return None if p is None else os.path.abspath(p)

        t = replace(self.train, ppo_config=absolute(self.train.ppo_config), env_config=absolute(self.train.env_config))
        return replace(self, runs_dir=absolute(self.runs_dir), results_md=absolute(self.results_md),
                       img_prefix=absolute(self.img_prefix), train=t)


def load_experiment_config(path: str | os.PathLike | None = None, overrides: Mapping | None = None) -> ExperimentConfig:
    """The packaged experiments.yaml, overlaid by the YAML at ``path`` (only the keys it changes)
    and then by ``overrides`` (a dict, dotted keys allowed); a bad key or value is a
    ``ConfigError`` naming the file (or 'overrides') and the dotted key."""
    cfg = config.load(ExperimentConfig, path, overrides)
    return replace(cfg, source=f"{path} over {PACKAGED_LABEL}" if path is not None else PACKAGED_LABEL)


def check_methods(methods) -> list[str]:
    bad = [m for m in methods if m not in CURRICULA]
    if bad:
        raise ExperimentError(f"unknown method(s) {bad}; expected some of {list(CURRICULA)}")
    return list(methods)
