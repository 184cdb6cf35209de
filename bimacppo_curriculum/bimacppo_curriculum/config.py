"""Configuration of the curriculum schedulers: small YAML files loaded into frozen dataclasses.

Every constant the paper leaves open lives in ``config/*.yaml`` next to this module, so a
run's behaviour is fully described by the file it loaded (docs/curriculum.md says why each
value was chosen); those files are the only place a default is written. The mechanism is
bimacppo_common.config: a user's file or dict lists only the keys it changes, on top of the
scheduler's packaged file, and loading is strict: an unknown key, a wrong type or a value out
of range raises ``ConfigError`` (a ``ValueError``) naming the file and the key, because a
silently ignored typo in a bandit constant would change a whole training run without anyone
noticing.
"""
from __future__ import annotations

import pathlib
from typing import Any, Mapping

from bimacppo_common import config
from bimacppo_common.config import ConfigError, Packaged, config_class, invalid, setting

CONFIG_DIR = pathlib.Path(__file__).resolve().parent / "config"


def _packaged(name: str) -> Packaged:
    return Packaged("bimacppo_curriculum", f"config/{name}")


class _Config:
    """Mixin: construction from the packaged default, a YAML overlay, a dict overlay or a saved dict."""

    FILE: str = ""

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "<dict>"):
        """A dict of keys (a saved ``to_dict()``, or a few overrides) over the packaged file."""
        return config.from_dict(cls, data, source)

    @classmethod
    def load(cls, path: str | pathlib.Path | None = None):
        """The packaged ``config/<FILE>``, overlaid by the YAML at ``path`` if given."""
        return config.load(cls, path)

    @classmethod
    def resolve(cls, config=None):
        """Accept None (packaged file), a path, a dict of overrides, or an instance."""
        if config is None:
            return cls()
        if isinstance(config, cls):
            return config
        if isinstance(config, (str, pathlib.Path)):
            return cls.load(config)
        if isinstance(config, Mapping):
            return cls.from_dict(config, source=f"overrides for {cls.FILE}")
        raise ConfigError(f"config for {cls.FILE} must be None, a path, a dict or a {cls.__name__}, "
                          f"got {type(config).__name__}")

    def to_dict(self) -> dict:
        return config.to_dict(self)


_N_SV_MAX = dict(lo=1, hi=16)
_POSITIVE = dict(lo=0.0, lo_open=True)
_SHARE = dict(lo=0.0, hi=1.0)


@config_class(_packaged("bimab.yaml"))
class BiMABConfig(_Config):
    """Constants of Algorithm 1 / eq. (11)-(17)."""

    FILE = "bimab.yaml"
    n_sv_max: int = setting(**_N_SV_MAX)
    eta: float = setting(lo=0.0, hi=1.0, lo_open=True)
    initial_weight: float
    sync_interval: int = setting(lo=1)
    min_syncs: int | None = setting(lo=1)
    step_budget: int | None = setting(lo=1)
    k0: float = setting(**_POSITIVE)
    k1: float = setting(**_POSITIVE)
    alpha_md: float = setting(**_POSITIVE)
    alpha_c: float = setting(**_POSITIVE)
    alpha_a: float = setting(**_POSITIVE)
    beta_c: float = setting(lo=0.0)
    beta_a: float = setting(lo=0.0)
    max_pending: int = setting(lo=0)

    def _check(self) -> None:
        if self.k1 < self.k0:
            raise invalid("k1", f"must be >= key 'k0' (else eq. (14)'s denominator can change sign), "
                                f"got k0={self.k0}, k1={self.k1}")


@config_class(_packaged("rd.yaml"))
class RDConfig(_Config):
    """RD-ACPPO (paper ref. [41]): a single Exp3.S level over N_sv, tasks uniform."""

    FILE = "rd.yaml"
    n_sv_max: int = setting(**_N_SV_MAX)
    eta: float = setting(lo=0.0, hi=1.0, lo_open=True)
    initial_weight: float
    sync_interval: int = setting(lo=1)
    min_syncs: int | None = setting(lo=1)
    step_budget: int | None = setting(lo=1)
    k0: float = setting(**_POSITIVE)
    k1: float = setting(**_POSITIVE)
    alpha_md: float = setting(**_POSITIVE)
    alpha_c: float = setting(**_POSITIVE)
    beta_c: float = setting(lo=0.0)
    max_pending: int = setting(lo=0)

    _check = BiMABConfig._check


@config_class(_packaged("manual.yaml"))
class ManualConfig(_Config):
    """Manual CPPO: hand-written stages over the episode budget plus a fixed epsilon."""

    FILE = "manual.yaml"
    n_sv_max: int = setting(**_N_SV_MAX)
    stages: tuple[int, ...] = setting(lo=0, hi=16, min_length=1)
    epsilon: float = setting(**_SHARE)

    def _check(self) -> None:
        bad = [s for s in self.stages if s > self.n_sv_max]
        if bad:
            raise invalid("stages", f"has N_sv {bad} above key 'n_sv_max'={self.n_sv_max}")


@config_class(_packaged("fixed.yaml"))
class FixedConfig(_Config):
    """Fixed PPO: always the hardest cluster."""

    FILE = "fixed.yaml"
    n_sv_max: int = setting(**_N_SV_MAX)


@config_class(_packaged("random.yaml"))
class RandomConfig(_Config):
    """Random CPPO: uniform over every scenario."""

    FILE = "random.yaml"
    n_sv_max: int = setting(**_N_SV_MAX)


@config_class(_packaged("synthetic.yaml"))
class SyntheticConfig(_Config):
    """A toy learner for checking the curriculum without the simulator (synthetic.py)."""

    FILE = "synthetic.yaml"
    n_sv_max: int = setting(**_N_SV_MAX)
    # returns, shaped like eq. (26)-(28)
    success_base: float = setting(lo=0.0)
    success_per_sv: float = setting(lo=0.0)
    success_per_pcp: float = setting(lo=0.0)
    pcp_per_sv: tuple[float, ...] = setting(lo=0.0, length=3)          # one per task (left, straight, right)
    collision_per_sv_speed: float = setting(lo=0.0)
    collision_speed_min: float = setting(lo=0.0)
    collision_speed_max: float = setting(lo=0.0)
    collision_share: float = setting(**_SHARE)
    timeout_return: float
    return_noise: float = setting(lo=0.0)
    # learner
    initial_competence: float = setting(**_SHARE)
    learn_rate: float = setting(**_SHARE)
    difficulty_per_sv: float = setting(lo=0.0)
    task_difficulty: tuple[float, ...] = setting(lo=0.0, length=3)     # one per task (left, straight, right)
    transfer_same_cluster: float = setting(**_SHARE)
    transfer_other_cluster: float = setting(**_SHARE)
    mastery: float = setting(lo=0.0, hi=1.0, lo_open=True)
    readiness_floor: float = setting(**_SHARE)

    def _check(self) -> None:
        if self.collision_speed_max < self.collision_speed_min:
            raise invalid("collision_speed_max", "must be >= key 'collision_speed_min'")
