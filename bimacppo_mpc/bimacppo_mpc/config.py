"""Configuration of the NMPC: a frozen dataclass loaded from ``config/mpc.yaml``.

Every number the controller uses lives in that YAML file (why each value was chosen is
in docs/mpc.md), so that the RL environment, the ROS node and the benchmark all run the
very same controller. Loading is strict: an unknown key, a missing key, a wrong type or
an out-of-range value is a ``ValueError`` naming the file and the key, because a typo in
a weight would otherwise silently give a different controller.
"""
from __future__ import annotations

import dataclasses
import math
import pathlib
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional

import yaml

CONFIG_DIR = pathlib.Path(__file__).resolve().parent / "config"
DEFAULT_PATH = CONFIG_DIR / "mpc.yaml"

HESSIANS = ("exact", "gauss_newton")
MAX_HORIZON = 200   # steps (20 s at dt = 0.1): far beyond use; a larger N only makes start-up hang
INITIAL_GUESSES = ("shifted", "hold", "zero", "brake", "speed")


def _is_real(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _check(cond: bool, key: str, msg: str) -> None:
    if not cond:
        raise ValueError(f"{key}: {msg}")


def _finite(key: str, value: Any) -> None:
    _check(_is_real(value) and math.isfinite(value), key, f"must be a finite number, got {value!r}")


def _int_at_least(key: str, value: Any, low: int) -> None:
    _check(isinstance(value, int) and not isinstance(value, bool), key, f"must be an integer, got {value!r}")
    _check(value >= low, key, f"must be >= {low}, got {value}")


@dataclass(frozen=True)
class FastSolverConfig:
    """The numba SQP: iterations are cheap, so the limits are generous (a non-converged solve is a fault)."""

    max_iter: int
    qp_max_iter: int
    tol: float
    hessian: str
    initial_guesses: tuple
    steer_bound_start: bool
    steer_bound_gate: bool
    threads: int
    parallel_min_batch: int

    def __post_init__(self):
        _check(isinstance(self.steer_bound_start, bool), "fast.steer_bound_start",
               f"must be true or false, got {self.steer_bound_start!r}")
        _check(isinstance(self.steer_bound_gate, bool), "fast.steer_bound_gate",
               f"must be true or false, got {self.steer_bound_gate!r}")
        _int_at_least("fast.threads", self.threads, 0)
        _int_at_least("fast.parallel_min_batch", self.parallel_min_batch, 1)
        _int_at_least("fast.max_iter", self.max_iter, 0)
        _int_at_least("fast.qp_max_iter", self.qp_max_iter, 1)
        _finite("fast.tol", self.tol)
        _check(0.0 < self.tol < 1.0, "fast.tol", f"must be in (0, 1), got {self.tol}")
        _check(self.hessian in HESSIANS, "fast.hessian", f"must be one of {HESSIANS}, got {self.hessian!r}")
        guesses = tuple(self.initial_guesses) if isinstance(self.initial_guesses, (list, tuple)) else None
        _check(guesses is not None and len(guesses) > 0, "fast.initial_guesses", "must be a non-empty list")
        for g in guesses:
            _check(g in INITIAL_GUESSES, "fast.initial_guesses", f"unknown guess {g!r}, known: {INITIAL_GUESSES}")
        _check(len(set(guesses)) == len(guesses), "fast.initial_guesses", "contains duplicates")
        object.__setattr__(self, "initial_guesses", guesses)


@dataclass(frozen=True)
class IpoptConfig:
    """The paper's reference solver; tol is IPOPT's own (scaled NLP error)."""

    max_iter: int
    tol: float
    print_level: int

    def __post_init__(self):
        _int_at_least("ipopt.max_iter", self.max_iter, 0)
        _finite("ipopt.tol", self.tol)
        _check(self.tol > 0.0, "ipopt.tol", f"must be > 0, got {self.tol}")
        _int_at_least("ipopt.print_level", self.print_level, 0)
        _check(self.print_level <= 12, "ipopt.print_level", f"must be <= 12, got {self.print_level}")


@dataclass(frozen=True)
class MPCConfig:
    """Model, bounds and weights of eq. (32)-(33); state order [x, y, v, psi], input [a, delta]."""

    wheelbase: float
    dt: float
    horizon: int
    a_min: float
    a_max: float
    delta_min: float
    delta_max: float
    v_min: float
    v_max: float
    q_x: tuple
    q_u: tuple
    q_du: tuple
    brake_decel: float
    relax_infeasible_speed_bounds: bool
    steer_rate_max: Optional[float]   # [rad/s] |delta_k - delta_{k-1}| <= steer_rate_max * dt; None: no bound
    jerk_max: Optional[float]         # [m/s^3] |a_0 - a_prev| <= jerk_max * dt (first move); None: no bound
    fast: FastSolverConfig
    ipopt: IpoptConfig
    source: str = field(default="<MPCConfig>", compare=False)

    def __post_init__(self):
        for key in ("wheelbase", "dt", "a_min", "a_max", "delta_min", "delta_max", "v_min", "v_max", "brake_decel"):
            _finite(key, getattr(self, key))
        _check(self.wheelbase > 0, "wheelbase", f"must be > 0, got {self.wheelbase}")
        _check(self.dt > 0, "dt", f"must be > 0, got {self.dt}")
        _int_at_least("horizon", self.horizon, 1)
        _check(self.horizon <= MAX_HORIZON, "horizon",
               f"must be <= {MAX_HORIZON} steps, got {self.horizon} (the dense solve grows with N^3)")
        # a = 0 must be admissible: standing still and cruising are then always feasible,
        # which is what makes the speed-bound tube of docs/mpc.md non-empty.
        _check(self.a_min <= 0.0 <= self.a_max and self.a_min < self.a_max, "a_min/a_max",
               f"need a_min <= 0 <= a_max and a_min < a_max, got [{self.a_min}, {self.a_max}]")
        _check(self.delta_min < self.delta_max, "delta_min/delta_max",
               f"need delta_min < delta_max, got [{self.delta_min}, {self.delta_max}]")
        _check(-math.pi / 2 < self.delta_min and self.delta_max < math.pi / 2, "delta_min/delta_max",
               "steering bounds must lie inside (-pi/2, pi/2)")
        _check(self.v_min < self.v_max, "v_min/v_max", f"need v_min < v_max, got [{self.v_min}, {self.v_max}]")
        _check(self.brake_decel <= 0.0, "brake_decel", f"must be <= 0 (a deceleration), got {self.brake_decel}")
        _check(isinstance(self.relax_infeasible_speed_bounds, bool), "relax_infeasible_speed_bounds",
               f"must be true or false, got {self.relax_infeasible_speed_bounds!r}")
        for key in ("steer_rate_max", "jerk_max"):
            val = getattr(self, key)
            if val is None:
                continue
            _finite(key, val)
            _check(val > 0.0, key, f"must be > 0 (null: no bound), got {val}")
            object.__setattr__(self, key, float(val))
        for key, size in (("q_x", 4), ("q_u", 2), ("q_du", 2)):
            val = getattr(self, key)
            _check(isinstance(val, (list, tuple)) and len(val) == size, key, f"must be a list of {size} numbers")
            for i, w in enumerate(val):
                _finite(f"{key}[{i}]", w)
                _check(w >= 0.0, f"{key}[{i}]", f"weights must be >= 0, got {w}")
            object.__setattr__(self, key, tuple(float(w) for w in val))
        for i in range(2):
            # q_u or q_du > 0 makes the reduced Hessian positive definite (strictly convex in U near x_ref).
            _check(self.q_u[i] + self.q_du[i] > 0.0, f"q_u[{i}]/q_du[{i}]", "at least one must be > 0")
        _check(isinstance(self.fast, FastSolverConfig), "fast", "must be a FastSolverConfig")
        _check(isinstance(self.ipopt, IpoptConfig), "ipopt", "must be an IpoptConfig")

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, path: str | pathlib.Path | None = None) -> "MPCConfig":
        """Read and validate a YAML file (default: the packaged ``config/mpc.yaml``)."""
        path = pathlib.Path(path) if path is not None else DEFAULT_PATH
        try:
            text = path.read_text()
        except OSError as exc:
            raise ValueError(f"{path}: cannot read MPC config ({exc})") from exc
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ValueError(f"{path}: invalid YAML ({exc})") from exc
        return cls.from_dict(data, source=str(path))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "<dict>") -> "MPCConfig":
        if not isinstance(data, Mapping):
            raise ValueError(f"{source}: top level must be a mapping, got {type(data).__name__}")
        try:
            top = _take(data, cls, prefix="", skip=("fast", "ipopt", "source"))
            top["fast"] = FastSolverConfig(**_take(_section(data, "fast"), FastSolverConfig, prefix="fast."))
            top["ipopt"] = IpoptConfig(**_take(_section(data, "ipopt"), IpoptConfig, prefix="ipopt."))
            _check_types(top)
            return cls(**top, source=source)
        except ValueError as exc:
            raise ValueError(f"{source}: {exc}") from None

    def replace(self, **changes) -> "MPCConfig":
        """A validated copy; nested sections accept dicts, e.g. ``cfg.replace(fast={"max_iter": 0})``."""
        for name, sub in (("fast", self.fast), ("ipopt", self.ipopt)):
            if isinstance(changes.get(name), Mapping):
                unknown = set(changes[name]) - {f.name for f in dataclasses.fields(sub)}
                if unknown:
                    raise ValueError(f"{name}: unknown key(s) {sorted(unknown)}")
                changes[name] = dataclasses.replace(sub, **changes[name])
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise ValueError(f"unknown key(s) {sorted(unknown)}")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("source")
        return d


def _section(data: Mapping[str, Any], name: str) -> Mapping[str, Any]:
    if name not in data:
        raise ValueError(f"{name}: missing section")
    sec = data[name]
    if not isinstance(sec, Mapping):
        raise ValueError(f"{name}: must be a mapping, got {type(sec).__name__}")
    return sec


def _take(data: Mapping[str, Any], cls, prefix: str, skip=()) -> dict:
    names = [f.name for f in dataclasses.fields(cls) if f.name not in ("source",)]
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ValueError(f"{prefix}{unknown[0]}: unknown key (known: {', '.join(names)})")
    out = {}
    for name in names:
        if name in skip:
            continue
        if name not in data:
            raise ValueError(f"{prefix}{name}: missing key")
        out[name] = data[name]
    return out


_FLOATS = ("wheelbase", "dt", "a_min", "a_max", "delta_min", "delta_max", "v_min", "v_max", "brake_decel")


def _check_types(top: dict) -> None:
    # YAML gives ints for "10"; accept them for float fields but nothing else (strings, bools, None).
    for key in _FLOATS:
        _finite(key, top[key])
        top[key] = float(top[key])
    _int_at_least("horizon", top["horizon"], 1)
