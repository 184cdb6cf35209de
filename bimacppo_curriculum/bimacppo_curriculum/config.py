"""Configuration of the curriculum schedulers: small YAML files loaded into frozen dataclasses.

Every constant the paper leaves open lives in ``config/*.yaml`` next to this module, so a
run's behaviour is fully described by the file it loaded (docs/curriculum.md says why each
value was chosen). Loading is strict: an unknown key, a missing key, a wrong type or a value
out of range raises ``ValueError`` naming the file and the key, because a silently ignored
typo in a bandit constant would change a whole training run without anyone noticing.
"""
from __future__ import annotations

import dataclasses
import math
import pathlib
from dataclasses import dataclass, field
from typing import Any, Mapping

import yaml

CONFIG_DIR = pathlib.Path(__file__).resolve().parent / "config"


def _rng(lo=None, hi=None, lo_open=False, hi_open=False):
    """Field metadata describing the allowed range (checked at load time)."""
    return {"lo": lo, "hi": hi, "lo_open": lo_open, "hi_open": hi_open}


def _check_range(value, meta, where):
    lo, hi = meta.get("lo"), meta.get("hi")
    if lo is not None and (value < lo or (meta.get("lo_open") and value == lo)):
        op = ">" if meta.get("lo_open") else ">="
        raise ValueError(f"{where}: must be {op} {lo}, got {value!r}")
    if hi is not None and (value > hi or (meta.get("hi_open") and value == hi)):
        op = "<" if meta.get("hi_open") else "<="
        raise ValueError(f"{where}: must be {op} {hi}, got {value!r}")


def _coerce(value, typ, where):
    """Accept exactly the YAML scalar kinds that mean the declared type (no bool-as-int)."""
    if typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{where}: expected a number, got {type(value).__name__} {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise ValueError(f"{where}: must be finite, got {value!r}")
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{where}: expected an integer, got {type(value).__name__} {value!r}")
        return int(value)
    if typ is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{where}: expected true/false, got {value!r}")
        return value
    if typ == "floats":
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{where}: expected a list of numbers, got {value!r}")
        return tuple(_coerce(v, float, f"{where}[{k}]") for k, v in enumerate(value))
    if typ == "ints":
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{where}: expected a list of integers, got {value!r}")
        return tuple(_coerce(v, int, f"{where}[{k}]") for k, v in enumerate(value))
    raise TypeError(f"unsupported config type {typ!r}")  # programming error, not user input


_TYPES = {"float": float, "int": int, "bool": bool, "tuple[float, ...]": "floats", "tuple[int, ...]": "ints"}


class _Config:
    """Mixin: strict construction from a mapping, a YAML file, or the packaged default."""

    FILE: str = ""

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "<dict>"):
        if not isinstance(data, Mapping):
            raise ValueError(f"{source}: expected a mapping of keys to values, got {type(data).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"{source}: unknown key(s) {unknown}; allowed: {sorted(names)}")
        missing = sorted(names - set(data))
        if missing:
            raise ValueError(f"{source}: missing key(s) {missing}")
        values = {}
        for f in dataclasses.fields(cls):
            where = f"{source}: key '{f.name}'"
            v = _coerce(data[f.name], _TYPES[f.type if isinstance(f.type, str) else f.type.__name__], where)
            meta = f.metadata
            if meta:
                for item in v if isinstance(v, tuple) else (v,):
                    _check_range(item, meta, where)
            values[f.name] = v
        obj = cls(**values)
        obj._validate(source)
        return obj

    def _validate(self, source: str) -> None:
        """Cross-field checks; overridden where keys constrain each other."""

    @classmethod
    def load(cls, path: str | pathlib.Path | None = None):
        path = pathlib.Path(path) if path is not None else CONFIG_DIR / cls.FILE
        try:
            text = path.read_text()
        except OSError as exc:
            raise ValueError(f"{path}: cannot read config file ({exc.strerror})") from exc
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ValueError(f"{path}: not valid YAML ({exc})") from exc
        return cls.from_dict(data if data is not None else {}, source=str(path))

    @classmethod
    def resolve(cls, config=None):
        """Accept None (packaged file), a path, a dict of overrides, or an instance."""
        if config is None:
            return cls.load()
        if isinstance(config, cls):
            return config
        if isinstance(config, (str, pathlib.Path)):
            return cls.load(config)
        if isinstance(config, Mapping):
            base = dataclasses.asdict(cls.load())
            unknown = sorted(set(config) - set(base))
            if unknown:
                raise ValueError(f"config overrides for {cls.FILE}: unknown key(s) {unknown}; allowed: {sorted(base)}")
            base.update(config)
            return cls.from_dict(base, source=f"{cls.FILE} + overrides")
        raise ValueError(f"config for {cls.FILE} must be None, a path, a dict or a {cls.__name__}, got {type(config).__name__}")

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}


@dataclass(frozen=True)
class BiMABConfig(_Config):
    """Constants of Algorithm 1 / eq. (11)-(17)."""

    FILE = "bimab.yaml"
    n_sv_max: int = field(metadata=_rng(1, 16))
    eta: float = field(metadata=_rng(0.0, 1.0, lo_open=True))
    initial_weight: float = field(metadata={})
    sync_interval: int = field(metadata=_rng(1))
    k0: float = field(metadata=_rng(0.0, lo_open=True))
    k1: float = field(metadata=_rng(0.0, lo_open=True))
    alpha_md: float = field(metadata=_rng(0.0, lo_open=True))
    alpha_c: float = field(metadata=_rng(0.0, lo_open=True))
    alpha_a: float = field(metadata=_rng(0.0, lo_open=True))
    beta_c: float = field(metadata=_rng(0.0))
    beta_a: float = field(metadata=_rng(0.0))
    max_pending: int = field(metadata=_rng(0))

    def _validate(self, source):
        if self.k1 < self.k0:
            raise ValueError(f"{source}: key 'k1' must be >= key 'k0' (else eq. (14)'s denominator can change sign), "
                             f"got k0={self.k0}, k1={self.k1}")


@dataclass(frozen=True)
class RDConfig(_Config):
    """RD-ACPPO (paper ref. [41]): a single Exp3.S level over N_sv, tasks uniform."""

    FILE = "rd.yaml"
    n_sv_max: int = field(metadata=_rng(1, 16))
    eta: float = field(metadata=_rng(0.0, 1.0, lo_open=True))
    initial_weight: float = field(metadata={})
    sync_interval: int = field(metadata=_rng(1))
    k0: float = field(metadata=_rng(0.0, lo_open=True))
    k1: float = field(metadata=_rng(0.0, lo_open=True))
    alpha_md: float = field(metadata=_rng(0.0, lo_open=True))
    alpha_c: float = field(metadata=_rng(0.0, lo_open=True))
    beta_c: float = field(metadata=_rng(0.0))
    max_pending: int = field(metadata=_rng(0))

    _validate = BiMABConfig._validate


@dataclass(frozen=True)
class ManualConfig(_Config):
    """Manual CPPO: hand-written stages over the episode budget plus a fixed epsilon."""

    FILE = "manual.yaml"
    n_sv_max: int = field(metadata=_rng(1, 16))
    stages: tuple[int, ...] = field(metadata=_rng(0, 16))
    epsilon: float = field(metadata=_rng(0.0, 1.0))

    def _validate(self, source):
        if not self.stages:
            raise ValueError(f"{source}: key 'stages' must list at least one N_sv")
        bad = [s for s in self.stages if s > self.n_sv_max]
        if bad:
            raise ValueError(f"{source}: key 'stages' has N_sv {bad} above key 'n_sv_max'={self.n_sv_max}")


@dataclass(frozen=True)
class FixedConfig(_Config):
    """Fixed PPO: always the hardest cluster."""

    FILE = "fixed.yaml"
    n_sv_max: int = field(metadata=_rng(1, 16))


@dataclass(frozen=True)
class RandomConfig(_Config):
    """Random CPPO: uniform over every scenario."""

    FILE = "random.yaml"
    n_sv_max: int = field(metadata=_rng(1, 16))


@dataclass(frozen=True)
class SyntheticConfig(_Config):
    """A toy learner for checking the curriculum without the simulator (synthetic.py)."""

    FILE = "synthetic.yaml"
    n_sv_max: int = field(metadata=_rng(1, 16))
    # returns, shaped like eq. (26)-(28)
    success_base: float = field(metadata=_rng(0.0))
    success_per_sv: float = field(metadata=_rng(0.0))
    success_per_pcp: float = field(metadata=_rng(0.0))
    pcp_per_sv: tuple[float, ...] = field(metadata=_rng(0.0))
    collision_per_sv_speed: float = field(metadata=_rng(0.0))
    collision_speed_min: float = field(metadata=_rng(0.0))
    collision_speed_max: float = field(metadata=_rng(0.0))
    collision_share: float = field(metadata=_rng(0.0, 1.0))
    timeout_return: float = field(metadata={})
    return_noise: float = field(metadata=_rng(0.0))
    # learner
    initial_competence: float = field(metadata=_rng(0.0, 1.0))
    learn_rate: float = field(metadata=_rng(0.0, 1.0))
    difficulty_per_sv: float = field(metadata=_rng(0.0))
    task_difficulty: tuple[float, ...] = field(metadata=_rng(0.0))
    transfer_same_cluster: float = field(metadata=_rng(0.0, 1.0))
    transfer_other_cluster: float = field(metadata=_rng(0.0, 1.0))
    mastery: float = field(metadata=_rng(0.0, 1.0, lo_open=True))
    readiness_floor: float = field(metadata=_rng(0.0, 1.0))

    def _validate(self, source):
        for key in ("pcp_per_sv", "task_difficulty"):
            if len(getattr(self, key)) != 3:
                raise ValueError(f"{source}: key '{key}' needs one value per task (left, straight, right)")
        if self.collision_speed_max < self.collision_speed_min:
            raise ValueError(f"{source}: key 'collision_speed_max' must be >= key 'collision_speed_min'")
