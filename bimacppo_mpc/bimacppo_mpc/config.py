"""Configuration of the NMPC: frozen dataclasses over the packaged ``config/mpc.yaml``.

Every number the controller uses lives in that YAML file (why each value was chosen is
in docs/mpc.md), so that the RL environment, the ROS node and the benchmark all run the
very same controller. The mechanism is ``bimacppo_common.config``: the packaged file is the
only place a default is written (``MPCConfig()`` is the packaged configuration), a user's
file lists only what it changes, and an unknown key (with the nearest known one suggested),
a wrong type or an out-of-range value is a ``ConfigError`` (a ``ValueError``) naming the file
and the dotted key, because a typo in a weight would otherwise silently give a different
controller.
"""
from __future__ import annotations

import dataclasses
import math
import pathlib
from typing import Any, Mapping

from bimacppo_common import config
from bimacppo_common.config import ConfigError, Packaged, config_class, invalid, runtime, setting

MPC_YAML = Packaged("bimacppo_mpc", "config/mpc.yaml")
DEFAULT_PATH = pathlib.Path(MPC_YAML.path)
CONFIG_DIR = DEFAULT_PATH.parent

HESSIANS = ("exact", "gauss_newton")
MAX_HORIZON = 200   # steps (20 s at dt = 0.1): far beyond use; a larger N only makes start-up hang
INITIAL_GUESSES = ("shifted", "hold", "zero", "brake", "speed")
_POSITIVE = dict(lo=0.0, lo_open=True)

__all__ = ["MPCConfig", "FastSolverConfig", "IpoptConfig", "ConfigError", "DEFAULT_PATH", "CONFIG_DIR",
           "HESSIANS", "INITIAL_GUESSES", "MAX_HORIZON"]


@config_class(MPC_YAML, "fast")
class FastSolverConfig:
    """The numba SQP: iterations are cheap, so the limits are generous (a non-converged solve is a fault)."""

    max_iter: int = setting(lo=0)
    qp_max_iter: int = setting(lo=1)
    tol: float = setting(lo=0.0, hi=1.0, lo_open=True, hi_open=True)
    hessian: str = setting(choices=HESSIANS)
    initial_guesses: tuple[str, ...] = setting(choices=INITIAL_GUESSES, min_length=1)
    steer_bound_start: bool
    steer_bound_gate: bool
    # False: a second start runs whichever side its bound lies on (runs recorded before the key)
    steer_bound_other_side: bool = setting(absent=False)
    # None: a second start always runs to convergence (runs recorded before the key ran that way)
    second_start_cut: float | None = setting(lo=1.0, absent=None)
    threads: int = setting(lo=0)
    parallel_min_batch: int = setting(lo=1)

    def _check(self) -> None:
        if len(set(self.initial_guesses)) != len(self.initial_guesses):
            raise invalid("initial_guesses", f"contains duplicates: {list(self.initial_guesses)}")


@config_class(MPC_YAML, "ipopt")
class IpoptConfig:
    """The paper's reference solver; tol is IPOPT's own (scaled NLP error)."""

    max_iter: int = setting(lo=0)
    tol: float = setting(**_POSITIVE)
    print_level: int = setting(lo=0, hi=12)


@config_class(MPC_YAML)
class MPCConfig:
    """Model, bounds and weights of eq. (32)-(33); state order [x, y, v, psi], input [a, delta]."""

    wheelbase: float = setting(**_POSITIVE)
    dt: float = setting(**_POSITIVE)
    # the dense solve grows with N^3: a horizon of millions would make start-up hang, not fail
    horizon: int = setting(lo=1, hi=MAX_HORIZON)
    a_min: float = setting(hi=0.0)
    a_max: float = setting(lo=0.0)
    delta_min: float = setting(lo=-math.pi / 2, lo_open=True)
    delta_max: float = setting(hi=math.pi / 2, hi_open=True)
    v_min: float
    v_max: float
    q_x: tuple[float, ...] = setting(lo=0.0, length=4)
    q_u: tuple[float, ...] = setting(lo=0.0, length=2)
    q_du: tuple[float, ...] = setting(lo=0.0, length=2)
    brake_decel: float = setting(hi=0.0)            # a deceleration
    relax_infeasible_speed_bounds: bool
    steer_rate_max: float | None = setting(**_POSITIVE)   # [rad/s]; None: no bound
    jerk_max: float | None = setting(**_POSITIVE)         # [m/s^3] on the first move; None: no bound
    fast: FastSolverConfig
    ipopt: IpoptConfig
    source: str = runtime("<MPCConfig>")             # the file (or dict) it was read from

    def _check(self) -> None:
        # a = 0 must be admissible: standing still and cruising are then always feasible,
        # which is what makes the speed-bound tube of docs/mpc.md non-empty.
        if not self.a_min < self.a_max:
            raise invalid("a_max", f"need a_min <= 0 <= a_max and a_min < a_max, got [{self.a_min}, {self.a_max}]")
        if not self.delta_min < self.delta_max:
            raise invalid("delta_max", f"need delta_min < delta_max, got [{self.delta_min}, {self.delta_max}]")
        if not self.v_min < self.v_max:
            raise invalid("v_max", f"need v_min < v_max, got [{self.v_min}, {self.v_max}]")
        for i in range(2):
            # q_u or q_du > 0 makes the reduced Hessian positive definite (strictly convex in U near x_ref).
            if not self.q_u[i] + self.q_du[i] > 0.0:
                raise invalid("q_du", f"q_u[{i}] or q_du[{i}] must be > 0")

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, path: str | pathlib.Path | None = None) -> "MPCConfig":
        """The packaged ``config/mpc.yaml``, overlaid by the YAML at ``path`` (it lists only what
        it changes)."""
        cfg = config.load(cls, path)
        return dataclasses.replace(cfg, source=str(path) if path is not None else MPC_YAML.path)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "<dict>") -> "MPCConfig":
        """A dict in the YAML's layout (all keys, or only those it changes) over the defaults."""
        return dataclasses.replace(config.from_dict(cls, data, source), source=source)

    @classmethod
    def from_record(cls, data: Mapping[str, Any], source: str = "<record>") -> "MPCConfig":
        """The config a run recorded, read as the controller it ran: a key added since takes the
        value that reproduces the code before it (``setting(absent=...)``), else its default."""
        return dataclasses.replace(config.from_record(cls, data, source), source=source)

    def replace(self, **changes) -> "MPCConfig":
        """A validated copy; nested sections accept dicts, e.g. ``cfg.replace(fast={"max_iter": 0})``."""
        changes = {k: config.to_dict(v) if config.is_config_class(type(v)) else v for k, v in changes.items()}
        out = config.build(type(self), (self.to_dict(), self.source), (changes, "replace"))
        return dataclasses.replace(out, source=self.source)

    def to_dict(self) -> dict:
        """Plain YAML types, the layout of mpc.yaml (``from_dict`` reads it back)."""
        return config.to_dict(self)
