"""PPO and training-loop configuration: `config/ppo.yaml` -> two frozen, validated dataclasses.

Kept free of torch so that reading or validating a config (CLI argument parsing, the ROS
planner node) never pays the torch import. The mechanism is bimacppo_common.config: the
packaged ppo.yaml is the only place a default is written (``PPOConfig()`` is the packaged
configuration), a user's file lists only what it changes, and validation runs in
``__post_init__`` so that ``dataclasses.replace(cfg, ...)`` overrides are checked exactly like
the file.
"""
from __future__ import annotations

import hashlib
import json
import pathlib
from typing import Mapping

from bimacppo_common import config
from bimacppo_common.config import ConfigError, Packaged, config_class, setting

PPO_YAML = Packaged("bimacppo_learning", "config/ppo.yaml")
DEFAULT_PATH = pathlib.Path(PPO_YAML.path)

ACTIVATIONS = ("tanh", "relu")
VECTOR_MODES = ("batched", "async", "sync")
SCHEDULES = ("constant", "linear")   # how a scheduled setting moves with the share of the budget done
_POSITIVE = dict(lo=0.0, lo_open=True)


@config_class(PPO_YAML, "ppo")
class PPOConfig:
    """The algorithm's constants; see docs/ppo.md for the reason behind each value."""

    hidden_sizes: tuple[int, ...] = setting(lo=1, min_length=1)
    activation: str = setting(choices=ACTIVATIONS)
    actor_lr: float = setting(**_POSITIVE)
    critic_lr: float = setting(**_POSITIVE)
    lr_schedule: str = setting(choices=SCHEDULES)
    lr_final_fraction: float = setting(lo=0.0, hi=1.0)
    adam_eps: float = setting(**_POSITIVE)
    epochs: int = setting(lo=1)
    gamma: float = setting(lo=0.0, hi=1.0)
    gae_lambda: float = setting(lo=0.0, hi=1.0)
    clip_eps: float = setting(lo=0.0, hi=1.0, lo_open=True, hi_open=True)
    minibatch_size: int = setting(lo=1)
    entropy_coef: float = setting(lo=0.0)
    entropy_schedule: str = setting(choices=SCHEDULES)
    entropy_final_fraction: float = setting(lo=0.0, hi=1.0)
    max_grad_norm: float = setting(**_POSITIVE)
    normalize_advantages: bool
    target_kl: float | None = setting(**_POSITIVE)
    obs_norm: bool
    obs_clip: float = setting(**_POSITIVE)
    obs_norm_eps: float = setting(**_POSITIVE)
    init_gain_hidden: float = setting(**_POSITIVE)
    init_gain_policy: float = setting(**_POSITIVE)
    init_gain_value: float = setting(**_POSITIVE)
    critic_warmup_updates: int = setting(lo=0)

    @staticmethod
    def schedule_fraction(schedule: str, final_fraction: float, progress: float) -> float:
        """The share of a scheduled setting in force after ``progress`` (0..1, clipped) of the
        budget: 1 throughout for ``constant``; for ``linear`` from 1 down to ``final_fraction``."""
        if schedule == "constant":
            return 1.0
        p = min(max(float(progress), 0.0), 1.0)
        return 1.0 - p * (1.0 - final_fraction)

    def lr_fraction(self, progress: float) -> float:
        """The share of actor_lr / critic_lr to use after ``progress`` (0..1) of the budget.

        ``linear`` falls from 1 to lr_final_fraction: late updates take smaller steps, so the
        policy a run ends with is not one large 20-epoch step away from a better one."""
        return self.schedule_fraction(self.lr_schedule, self.lr_final_fraction, progress)

    def entropy_coef_at(self, progress: float) -> float:
        """The entropy bonus after ``progress`` (0..1) of the budget.

        ``linear`` lowers it from entropy_coef to entropy_final_fraction x entropy_coef: the
        bonus that keeps the heads exploring early stops holding the trained policy's
        distributions wide, so the action it is deployed with (median or argmax) is the one it
        was trained to take rather than the centre of a wide distribution."""
        return self.entropy_coef * self.schedule_fraction(self.entropy_schedule, self.entropy_final_fraction,
                                                          progress)


@config_class(PPO_YAML, "train")
class TrainConfig:
    """The loop's constants (vectorisation, rollout size, checkpoints, logging)."""

    num_envs: int = setting(lo=1)
    vector: str = setting(choices=VECTOR_MODES)
    batch_workers: int = setting(lo=1)
    rollout_steps: int = setting(lo=1)
    checkpoint_every: int = setting(lo=1)
    keep_checkpoints: int = setting(lo=1)
    success_window: int = setting(lo=1)
    tensorboard: bool
    tensorboard_every: int = setting(lo=1)
    progress_bar: bool
    torch_threads: int = setting(lo=1)
    update_threads: int = setting(lo=0)
    critic_thread: bool
    seed: int = setting(lo=0)

    @property
    def workers(self) -> int:
        """Processes of the batched vector env: batch_workers, never more than one per env
        (so ``--num-envs 1`` needs no second setting)."""
        return min(self.batch_workers, self.num_envs)


@config_class(PPO_YAML)
class PPOFile:
    """The layout of ppo.yaml (and of a checkpoint's saved config): both sections."""

    ppo: PPOConfig
    train: TrainConfig


def load_config(path: str | pathlib.Path | None = None, *, ppo: Mapping | None = None,
                train: Mapping | None = None) -> tuple[PPOConfig, TrainConfig]:
    """The packaged ppo.yaml, overlaid by the YAML at ``path`` (a variant lists only what it
    changes), then by the per-section overrides ``ppo`` and ``train``.

    Every error names the file (or 'overrides') and the offending key.
    """
    overrides = {name: dict(sec) for name, sec in (("ppo", ppo), ("train", train)) if sec}
    f = config.load(PPOFile, path, overrides)
    return f.ppo, f.train


def config_to_dict(pcfg: PPOConfig, tcfg: TrainConfig | None = None) -> dict:
    """Plain-type dict (lists, not tuples) for checkpoints, JSON and hashing."""
    out = {"ppo": config.to_dict(pcfg)}
    if tcfg is not None:
        out["train"] = config.to_dict(tcfg)
    return out


def config_from_dict(d: Mapping, source: str = "checkpoint") -> tuple[PPOConfig, TrainConfig | None]:
    """Read ``config_to_dict`` output back (keys saved before they existed take the packaged
    defaults); the TrainConfig is None when ``d`` has no 'train' section."""
    if not isinstance(d, Mapping):
        raise ConfigError(f"expected a mapping with sections 'ppo' and 'train', got {type(d).__name__}",
                          source=source)
    f = config.from_dict(PPOFile, d, source)
    return f.ppo, (f.train if d.get("train") is not None else None)


def config_hash(pcfg: PPOConfig) -> str:
    """Short stable hash of the algorithm config: lets a deployed policy say what trained it."""
    blob = json.dumps(config_to_dict(pcfg)["ppo"], sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:16]
