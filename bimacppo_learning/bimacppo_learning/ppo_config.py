"""PPO and training-loop configuration: `config/ppo.yaml` -> two frozen, validated dataclasses.

Kept free of torch so that reading or validating a config (CLI argument parsing, the ROS
planner node) never pays the torch import.  Validation lives in ``__post_init__`` so that
``dataclasses.replace(cfg, ...)`` overrides are checked exactly like the file.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import pathlib
from dataclasses import dataclass, fields
from typing import Any, Mapping

import yaml

DEFAULT_PATH = pathlib.Path(__file__).resolve().parent / "config" / "ppo.yaml"

ACTIVATIONS = ("tanh", "relu")
VECTOR_MODES = ("batched", "async", "sync")


def _fail(key: str, value: Any, why: str) -> None:
    raise ValueError(f"{key}={value!r}: {why}")


def _number(key: str, value: Any, lo: float | None = None, hi: float | None = None,
            lo_open: bool = False, hi_open: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        _fail(key, value, "must be a finite number")
    if lo is not None and (value <= lo if lo_open else value < lo):
        _fail(key, value, f"must be {'>' if lo_open else '>='} {lo}")
    if hi is not None and (value >= hi if hi_open else value > hi):
        _fail(key, value, f"must be {'<' if hi_open else '<='} {hi}")


def _integer(key: str, value: Any, lo: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        _fail(key, value, "must be an integer")
    if value < lo:
        _fail(key, value, f"must be >= {lo}")


def _boolean(key: str, value: Any) -> None:
    if not isinstance(value, bool):
        _fail(key, value, "must be true or false")


@dataclass(frozen=True)
class PPOConfig:
    """The algorithm's constants; see docs/ppo.md for the reason behind each value."""

    hidden_sizes: tuple[int, ...] = (256, 128)
    activation: str = "tanh"
    actor_lr: float = 5e-4
    critic_lr: float = 1e-3
    adam_eps: float = 1e-5
    epochs: int = 20
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    minibatch_size: int = 512
    entropy_coef: float = 0.01
    max_grad_norm: float = 0.5
    normalize_advantages: bool = True
    target_kl: float | None = None
    obs_norm: bool = True
    obs_clip: float = 10.0
    obs_norm_eps: float = 1e-8
    init_gain_hidden: float = math.sqrt(2.0)
    init_gain_policy: float = 0.01
    init_gain_value: float = 1.0

    def __post_init__(self) -> None:
        hs = self.hidden_sizes
        if isinstance(hs, list):
            object.__setattr__(self, "hidden_sizes", tuple(hs))
            hs = self.hidden_sizes
        if not isinstance(hs, tuple) or len(hs) == 0:
            _fail("hidden_sizes", hs, "must be a non-empty list of layer widths")
        for k, h in enumerate(hs):
            _integer(f"hidden_sizes[{k}]", h, 1)
        if self.activation not in ACTIVATIONS:
            _fail("activation", self.activation, f"must be one of {ACTIVATIONS}")
        _number("actor_lr", self.actor_lr, 0, lo_open=True)
        _number("critic_lr", self.critic_lr, 0, lo_open=True)
        _number("adam_eps", self.adam_eps, 0, lo_open=True)
        _integer("epochs", self.epochs, 1)
        _number("gamma", self.gamma, 0, 1, hi_open=False)
        _number("gae_lambda", self.gae_lambda, 0, 1)
        _number("clip_eps", self.clip_eps, 0, 1, lo_open=True, hi_open=True)
        _integer("minibatch_size", self.minibatch_size, 1)
        _number("entropy_coef", self.entropy_coef, 0)
        _number("max_grad_norm", self.max_grad_norm, 0, lo_open=True)
        _boolean("normalize_advantages", self.normalize_advantages)
        if self.target_kl is not None:
            _number("target_kl", self.target_kl, 0, lo_open=True)
        _boolean("obs_norm", self.obs_norm)
        _number("obs_clip", self.obs_clip, 0, lo_open=True)
        _number("obs_norm_eps", self.obs_norm_eps, 0, lo_open=True)
        _number("init_gain_hidden", self.init_gain_hidden, 0, lo_open=True)
        _number("init_gain_policy", self.init_gain_policy, 0, lo_open=True)
        _number("init_gain_value", self.init_gain_value, 0, lo_open=True)


@dataclass(frozen=True)
class TrainConfig:
    """The loop's constants (vectorisation, rollout size, checkpoints, logging)."""

    num_envs: int = 2
    vector: str = "async"
    batch_workers: int = 1
    rollout_steps: int = 1024
    checkpoint_every: int = 100
    keep_checkpoints: int = 3
    success_window: int = 100
    tensorboard: bool = True
    progress_bar: bool = True
    torch_threads: int = 1
    update_threads: int = 0
    seed: int = 0

    def __post_init__(self) -> None:
        _integer("num_envs", self.num_envs, 1)
        _integer("batch_workers", self.batch_workers, 1)
        if self.batch_workers > self.num_envs:
            _fail("batch_workers", self.batch_workers, f"must be <= num_envs ({self.num_envs})")
        if self.vector not in VECTOR_MODES:
            _fail("vector", self.vector, f"must be one of {VECTOR_MODES}")
        _integer("rollout_steps", self.rollout_steps, 1)
        _integer("checkpoint_every", self.checkpoint_every, 1)
        _integer("keep_checkpoints", self.keep_checkpoints, 1)
        _integer("success_window", self.success_window, 1)
        _boolean("tensorboard", self.tensorboard)
        _boolean("progress_bar", self.progress_bar)
        _integer("torch_threads", self.torch_threads, 1)
        _integer("update_threads", self.update_threads, 0)
        _integer("seed", self.seed, 0)


def _build(cls, section: str, raw: Any, source: str):
    if raw is None:
        raw = {}
    if not isinstance(raw, Mapping):
        raise ValueError(f"{source}: section '{section}' must be a mapping, got {type(raw).__name__}")
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ValueError(f"{source}: unknown key(s) in '{section}': {unknown}; known: {sorted(known)}")
    try:
        return cls(**raw)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{source}: in '{section}': {exc}") from None


def load_config(path: str | pathlib.Path | None = None, *, ppo: Mapping | None = None,
                train: Mapping | None = None) -> tuple[PPOConfig, TrainConfig]:
    """Read a ppo.yaml (default: the packaged one) and apply optional per-section overrides.

    Every error names the file (or 'overrides') and the offending key.
    """
    path = pathlib.Path(path) if path is not None else DEFAULT_PATH
    source = str(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"{source}: cannot read PPO config: {exc.strerror or exc}") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"{source}: not valid YAML: {exc}") from None
    if doc is None:
        doc = {}
    if not isinstance(doc, Mapping):
        raise ValueError(f"{source}: top level must be a mapping with sections 'ppo' and 'train'")
    unknown = sorted(set(doc) - {"ppo", "train"})
    if unknown:
        raise ValueError(f"{source}: unknown section(s) {unknown}; expected 'ppo' and 'train'")
    ppo_raw, train_raw = doc.get("ppo") or {}, doc.get("train") or {}
    for name, sec in (("ppo", ppo_raw), ("train", train_raw)):
        if not isinstance(sec, Mapping):
            raise ValueError(f"{source}: section '{name}' must be a mapping, got {type(sec).__name__}")
    ppo_raw, train_raw = dict(ppo_raw), dict(train_raw)
    pcfg = _build(PPOConfig, "ppo", ppo_raw, source)
    tcfg = _build(TrainConfig, "train", train_raw, source)
    if ppo:
        pcfg = _build(PPOConfig, "ppo", {**ppo_raw, **ppo}, f"{source} + overrides")
    if train:
        tcfg = _build(TrainConfig, "train", {**train_raw, **train}, f"{source} + overrides")
    return pcfg, tcfg


def config_to_dict(pcfg: PPOConfig, tcfg: TrainConfig | None = None) -> dict:
    """Plain-type dict (lists, not tuples) for checkpoints, JSON and hashing."""
    out = {"ppo": dataclasses.asdict(pcfg)}
    out["ppo"]["hidden_sizes"] = list(pcfg.hidden_sizes)
    if tcfg is not None:
        out["train"] = dataclasses.asdict(tcfg)
    return out


def config_from_dict(d: Mapping, source: str = "checkpoint") -> tuple[PPOConfig, TrainConfig | None]:
    pcfg = _build(PPOConfig, "ppo", d.get("ppo", {}), source)
    tcfg = _build(TrainConfig, "train", d["train"], source) if d.get("train") is not None else None
    return pcfg, tcfg


def config_hash(pcfg: PPOConfig) -> str:
    """Short stable hash of the algorithm config: lets a deployed policy say what trained it."""
    blob = json.dumps(config_to_dict(pcfg)["ppo"], sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:16]
