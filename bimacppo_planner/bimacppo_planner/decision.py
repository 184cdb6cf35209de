"""The RL agent's view of the world: observation (eq. 18-20) and action decoding (§III-C).

Both the Gymnasium environment (training, in-process evaluation) and the ROS planner
node use this module on plain arrays, so an observation computed from ROS messages is
bit-identical to the one computed in-process. Nothing here knows about the simulator's
internals: it needs the EV state, the SV states, the goal pose, the A* waypoint set and
the road's `lateral_point` (for the lane-change sub-action).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

TWO_PI = 2.0 * math.pi


def wrap_angle(a: float) -> float:
    """Wrap to (-pi, pi]: heading differences must not jump by 2*pi (observation and MPC)."""
    a = math.fmod(a + math.pi, TWO_PI)
    if a <= 0.0:
        a += TWO_PI
    return a - math.pi


class ConfigError(ValueError):
    """A configuration file or value is invalid; the message names the file and the key."""


@dataclass(frozen=True)
class ObservationConfig:
    max_sv: int = 3
    sv_clip: float = 7.5
    sv_order: str = "distance"
    pad_value: tuple = (7.5, 7.5, 0.0, 0.0)
    sv_frame: str = "paper"   # paper: |dx|, |dy| in the map frame (eq. 20); ego: signed, in the EV's frame

    def validate(self, where: str) -> None:
        if not (isinstance(self.max_sv, int) and 0 <= self.max_sv <= 16):
            raise ConfigError(f"{where}: observation.max_sv must be an integer in [0, 16], got {self.max_sv!r}")
        if not (self.sv_clip > 0 and math.isfinite(self.sv_clip)):
            raise ConfigError(f"{where}: observation.sv_clip must be a positive number, got {self.sv_clip!r}")
        if self.sv_order not in ("distance", "id"):
            raise ConfigError(f"{where}: observation.sv_order must be 'distance' or 'id', got {self.sv_order!r}")
        if self.sv_frame not in ("paper", "ego"):
            raise ConfigError(f"{where}: observation.sv_frame must be 'paper' or 'ego', got {self.sv_frame!r}")
        if len(self.pad_value) != 4 or not all(math.isfinite(float(v)) for v in self.pad_value):
            raise ConfigError(f"{where}: observation.pad_value must be 4 finite numbers, got {self.pad_value!r}")


@dataclass(frozen=True)
class ActionConfig:
    n_waypoints: int = 5
    speeds: tuple = (0.0, 2.0, 4.0, 6.0, 8.0)
    lane_change: tuple = (-1, 0, 1)
    decision_every: int = 1

    def validate(self, where: str) -> None:
        if not (isinstance(self.n_waypoints, int) and self.n_waypoints >= 1):
            raise ConfigError(f"{where}: action.n_waypoints must be an integer >= 1, got {self.n_waypoints!r}")
        if len(self.speeds) < 1 or any((not math.isfinite(float(s))) or s < 0 for s in self.speeds):
            raise ConfigError(f"{where}: action.speeds must be finite non-negative numbers, got {self.speeds!r}")
        if tuple(self.lane_change) != (-1, 0, 1):
            raise ConfigError(f"{where}: action.lane_change must be [-1, 0, 1] (left, keep, right), got {self.lane_change!r}")
        if not (isinstance(self.decision_every, int) and self.decision_every >= 1):
            raise ConfigError(f"{where}: action.decision_every must be an integer >= 1, got {self.decision_every!r}")


@dataclass(frozen=True)
class RewardConfig:
    success_base: float = 10.0
    alpha1: float = 2.0
    alpha2: float = 0.5
    alpha3: float = 10.0
    r_f_max: float = 3.0
    collision_base: float = -10.0
    alpha4: float = -1.0
    timeout: float = -5.0
    lane_change: float = -0.05
    step: float = -0.02

    def validate(self, where: str) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"{where}: reward.{f.name} must be a finite number, got {v!r}")
        if self.alpha4 > 0 or self.collision_base > 0:
            raise ConfigError(f"{where}: reward.alpha4 and reward.collision_base are penalties and must be <= 0")


@dataclass(frozen=True)
class EnvConfig:
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    action: ActionConfig = field(default_factory=ActionConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)

    @classmethod
    def load(cls, path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> "EnvConfig":
        """Load the YAML (default: the packaged ``config/env.yaml``); unknown keys are errors."""
        if path is None:
            where = "bimacppo_planner/config/env.yaml"
            text = resources.files("bimacppo_planner").joinpath("config/env.yaml").read_text()
        else:
            where = str(path)
            try:
                text = Path(path).read_text()
            except OSError as exc:
                raise ConfigError(f"{where}: cannot read environment config: {exc}") from exc
        try:
            raw = yaml.safe_load(text) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{where}: not valid YAML: {exc}") from exc
        if not isinstance(raw, dict):
            raise ConfigError(f"{where}: top level must be a mapping, got {type(raw).__name__}")
        for key, value in (overrides or {}).items():  # "reward.step": -0.1
            sec, _, name = key.partition(".")
            if not name or not isinstance(raw.setdefault(sec, {}), dict):
                raise ConfigError(f"{where}: bad override key {key!r}; use 'section.key'")
            raw[sec] = {**raw[sec], name: value}
        return cls.from_dict(raw, where)

    @classmethod
    def from_dict(cls, raw: Mapping[str, Any], where: str = "<dict>") -> "EnvConfig":
        sections = {"observation": ObservationConfig, "action": ActionConfig, "reward": RewardConfig}
        unknown = set(raw) - set(sections)
        if unknown:
            raise ConfigError(f"{where}: unknown section(s) {sorted(unknown)}; expected {sorted(sections)}")
        built = {}
        for name, klass in sections.items():
            sub = raw.get(name) or {}
            if not isinstance(sub, Mapping):
                raise ConfigError(f"{where}: section '{name}' must be a mapping")
            known = {f.name for f in fields(klass)}
            bad = set(sub) - known
            if bad:
                raise ConfigError(f"{where}: unknown key(s) {sorted(f'{name}.{b}' for b in bad)}")
            vals = {k: (tuple(v) if isinstance(v, list) else v) for k, v in sub.items()}
            try:
                obj = klass(**vals)
            except TypeError as exc:
                raise ConfigError(f"{where}: section '{name}': {exc}") from exc
            obj.validate(where)
            built[name] = obj
        return cls(**built)

    def to_dict(self) -> dict:
        out = {}
        for sec in ("observation", "action", "reward"):
            obj = getattr(self, sec)
            out[sec] = {f.name: (list(getattr(obj, f.name)) if isinstance(getattr(obj, f.name), tuple) else getattr(obj, f.name))
                        for f in fields(obj)}
        return out

    @property
    def obs_dim(self) -> int:
        return 4 * (1 + self.observation.max_sv)

    @property
    def nvec(self) -> tuple[int, int, int]:
        return (self.action.n_waypoints, len(self.action.speeds), len(self.action.lane_change))


def observe(cfg: ObservationConfig, ego: np.ndarray, goal: np.ndarray, svs: np.ndarray) -> np.ndarray:
    """Eq. (18)-(20): EV features relative to the goal, then one row per SV, padded to N_sv^max.

    SVs beyond N_sv^max are dropped farthest-first (the nearest ones matter for safety).
    """
    x, y, v, psi = (float(ego[0]), float(ego[1]), float(ego[2]), float(ego[3]))
    out = np.empty(4 * (1 + cfg.max_sv), dtype=np.float32)
    out[0] = abs(x - float(goal[0]))
    out[1] = abs(y - float(goal[1]))
    out[2] = v
    out[3] = wrap_angle(psi - float(goal[2]))
    svs = np.asarray(svs, dtype=np.float64).reshape(-1, 4)
    if cfg.sv_order == "distance" and len(svs) > 1:
        order = np.argsort(np.hypot(svs[:, 0] - x, svs[:, 1] - y), kind="stable")
        svs = svs[order]
    c = cfg.sv_clip
    ego_frame = cfg.sv_frame == "ego"
    cp, sp = math.cos(psi), math.sin(psi)
    for k in range(cfg.max_sv):
        o = 4 + 4 * k
        if k < len(svs):
            sx, sy, sv, spsi = svs[k]
            if ego_frame:
                # an extension (docs/method.md): where the SV is relative to the EV, ahead/behind and
                # left/right kept, which eq. (20)'s absolute values discard
                dx, dy = sx - x, sy - y
                out[o] = min(max(cp * dx + sp * dy, -c), c)
                out[o + 1] = min(max(-sp * dx + cp * dy, -c), c)
            else:
                out[o] = min(abs(x - sx), c)
                out[o + 1] = min(abs(y - sy), c)
            out[o + 2] = v - sv
            out[o + 3] = wrap_angle(psi - spsi)
        else:
            out[o:o + 4] = cfg.pad_value
    return out


class WaypointTracker:
    """Keeps the reference waypoint set of §III-C and offers A1.

    Waypoints behind the EV are removed (monotonically: a waypoint once passed never
    comes back, as in the paper); A1 is the next ``n`` of those left, WP0 nearest, which
    is what lets the policy stop or yield by choosing WP0. Near the goal, when fewer than
    ``n`` remain, the last waypoint is repeated so the action space keeps its size.
    """

    def __init__(self, route: np.ndarray, n: int):
        route = np.asarray(route, dtype=np.float64)
        if route.ndim != 2 or route.shape[1] != 3 or len(route) == 0 or not np.all(np.isfinite(route)):
            raise ValueError(f"route must be a non-empty finite (M, 3) array of [x, y, psi], got shape {route.shape}")
        self.route = route
        self.n = n
        self.idx = 0
        self._cos = np.cos(route[:, 2])
        self._sin = np.sin(route[:, 2])

    def update(self, x: float, y: float) -> None:
        r, m = self.route, len(self.route) - 1
        i = self.idx
        while i < m and (r[i, 0] - x) * self._cos[i] + (r[i, 1] - y) * self._sin[i] < 0.0:
            i += 1
        self.idx = i

    def candidates(self) -> np.ndarray:
        j = np.minimum(np.arange(self.idx, self.idx + self.n), len(self.route) - 1)
        return self.route[j]


def decode_action(action, tracker: WaypointTracker, cfg: ActionConfig, lateral_point) -> tuple[np.ndarray, bool]:
    """MultiDiscrete action -> x_IMR = [x, y, v, psi] (eq. 31), and whether a lane change was taken.

    ``lateral_point(x, y, psi, side)`` gives the matching point on the adjacent lane or None;
    where there is no adjacent lane the waypoint stays (and it does not count as a lane change).
    """
    a1, a2, a3 = int(action[0]), int(action[1]), int(action[2])
    if not (0 <= a1 < cfg.n_waypoints and 0 <= a2 < len(cfg.speeds) and 0 <= a3 < len(cfg.lane_change)):
        raise ValueError(f"action {tuple(action)} outside MultiDiscrete({[cfg.n_waypoints, len(cfg.speeds), len(cfg.lane_change)]})")
    wx, wy, wpsi = tracker.candidates()[a1]
    side = cfg.lane_change[a3]
    changed = False
    if side != 0:
        p = lateral_point(float(wx), float(wy), float(wpsi), int(side))
        if p is not None:
            wx, wy, wpsi = float(p[0]), float(p[1]), float(p[2])
            changed = True
    return np.array([wx, wy, float(cfg.speeds[a2]), wpsi], dtype=np.float64), changed


def step_reward(cfg: RewardConfig, lane_change: bool, outcome: str | None = None, n_sv: int = 0,
                n_pcp: int = 0, ev_speed: float = 0.0, dist_to_goal: float = 0.0) -> float:
    """Eq. (26)-(28) for one decision: the per-step and lane-change terms, plus the terminal
    term when ``outcome`` is set. Shared by the environment and the ROS planner node, which
    reports episode returns to the curriculum."""
    r = cfg.step + (cfg.lane_change if lane_change else 0.0)
    if outcome is None:
        return r
    if outcome == "success":
        return r + cfg.success_base + cfg.alpha1 * n_sv + cfg.alpha2 * n_pcp
    if outcome not in ("collision", "timeout"):
        raise ValueError(f"unknown outcome {outcome!r}")
    r += min(cfg.r_f_max, cfg.alpha3 / max(float(dist_to_goal), 1e-3))
    if outcome == "collision":
        r += cfg.collision_base + cfg.alpha4 * n_sv * float(ev_speed)
    else:
        r += cfg.timeout
    return r
