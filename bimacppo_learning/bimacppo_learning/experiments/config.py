"""The experiments config: the packaged experiments.yaml, a user's YAML and overrides on top,
validated key by key into frozen dataclasses; the layout of every output path lives here."""
from __future__ import annotations

import os
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, Mapping

import yaml

from bimacppo_sim import TASKS

from .validate import choice, integer, items, number, optional, text

CONFIG_PATH = Path(__file__).resolve().parent.parent / "config" / "experiments.yaml"
PACKAGED_LABEL = "bimacppo_learning/config/experiments.yaml (packaged)"
CURRICULA = ("bimab", "fixed", "random", "manual", "rd")
MAPS = ("dual_lane_4way", "single_lane_4way", "three_lane_straight")
DRIVERS = ("go", "yield")
METHOD_NAMES = {"bimab": "BiM-ACPPO", "fixed": "Fixed PPO", "random": "Random CPPO",
                "manual": "Manual CPPO", "rd": "RD-ACPPO", "go": 'scripted "go"', "yield": 'scripted "yield"'}
OUTCOMES = ("success", "collision", "timeout")


class ExperimentError(Exception):
    """A problem the user must fix (bad config, missing run, corrupt file): printed, exit code 2."""


@dataclass(frozen=True)
class TrainSection:
    num_envs: int
    vector: str
    mpc: str
    ppo_config: str | None
    poll_s: float
    env_config: str | None = None
    num_cpus: int = 2


@dataclass(frozen=True)
class EvalSection:
    episodes: int
    n_sv: tuple
    tasks: tuple
    workers: int
    reference_drivers: tuple
    num_cpus: int = 2


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
    source: str = PACKAGED_LABEL

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


SCHEMA: dict[str, Any] = {
    "methods": items(choice(CURRICULA)),
    "seeds": items(integer(0)),
    "episodes": integer(1),
    "train_map": choice(MAPS),
    "zero_shot_map": optional(choice(MAPS)),
    "runs_dir": text(),
    "results_md": text(),
    "img_prefix": text(),
    "train": {"num_envs": integer(1, 64), "vector": choice(("batched", "async", "sync")),
              "mpc": choice(("fast", "ipopt")), "ppo_config": text(optional=True),
              "poll_s": number(0.0, lo_open=True), "env_config": text(optional=True), "num_cpus": integer(1, 256)},
    "evaluation": {"episodes": integer(1, 1000), "n_sv": items(integer(0, 3)), "tasks": items(choice(TASKS)),
                   "workers": integer(1, 64), "reference_drivers": items(choice(DRIVERS), nonempty=False),
                   "num_cpus": integer(1, 256)},
    "overtake": {"map": choice(MAPS), "source_method": choice(CURRICULA), "curriculum": choice(CURRICULA),
                 "n_slow_max": integer(0, 3), "episodes": integer(1), "seed": integer(0),
                 "test_episodes": integer(1, 1000), "test_n_sv": integer(0, 3)},
    "report": {"window": integer(1), "efficiency_fraction": number(0.0, 1.0, lo_open=True),
               "figure_seed": integer(0)},
}
SECTIONS = {"train": TrainSection, "evaluation": EvalSection, "overtake": OvertakeSection, "report": ReportSection}


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
    (a dict) on top; every error is an ExperimentError (what the CLI reports) naming the file
    and the key."""
    base = _read_yaml(CONFIG_PATH)
    origin = {k: str(CONFIG_PATH) for k in base}
    layers = []
    if path is not None:
        layers.append((str(path), _read_yaml(Path(path))))
    if overrides:
        layers.append(("overrides", dict(overrides)))
    for src, doc in layers:
        for key, val in doc.items():
            if key not in SCHEMA:
                raise ExperimentError(f"{src}: unknown key '{key}' (expected one of {sorted(SCHEMA)})")
            if isinstance(SCHEMA[key], dict):
                if not isinstance(val, dict):
                    raise ExperimentError(f"{src}: key '{key}' must be a mapping, got {val!r}")
                for sub in val:
                    if sub not in SCHEMA[key]:
                        raise ExperimentError(f"{src}: unknown key '{key}.{sub}' "
                                              f"(expected one of {sorted(SCHEMA[key])})")
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
        check = SCHEMA[key][sub] if sub is not None else SCHEMA[key]
        err = check(v)
        if err:
            raise ExperimentError(f"{src}: key '{name}' {err}")
        return tuple(v) if isinstance(v, list) else v

    kw = {}
    for key, spec in SCHEMA.items():
        if isinstance(spec, dict):
            cls = SECTIONS[key]
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
    return ExperimentConfig(**kw, source=f"{path} over {PACKAGED_LABEL}" if path is not None else PACKAGED_LABEL)


def check_methods(methods) -> list[str]:
    bad = [m for m in methods if m not in CURRICULA]
    if bad:
        raise ExperimentError(f"unknown method(s) {bad}; expected some of {list(CURRICULA)}")
    return list(methods)
