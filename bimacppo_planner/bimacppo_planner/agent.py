"""The deployed high-level planner: policy + observation + action decoding, on plain arrays.

The ROS planner node and in-process evaluation both drive this class, and the training
environment uses the same functions (``decision.py``), so a planner fed from ROS messages
computes exactly what the environment computed during training.
"""
from __future__ import annotations

import math
from importlib import resources
from pathlib import Path

import numpy as np

from bimacppo_sim import RoadMap, WorldConfig, load_map
from bimacppo_sim.world import reference_route

from .policy import CheckpointError, Policy
from .decision import EnvConfig, WaypointTracker, decode_action, observe

SHIPPED_POLICY = "policies/bimacppo_dual_lane.pt"


def shipped_policy_path() -> Path:
    """The BiM-ACPPO policy trained on the dual-lane intersection that ships in the package."""
    return Path(str(resources.files("bimacppo_planner").joinpath(SHIPPED_POLICY)))


def load_policy(path: str | Path | None = None) -> Policy:
    """A policy export or a full training checkpoint; None (or "" / "shipped") means the shipped policy."""
    path = shipped_policy_path() if path is None or str(path) in ("", "shipped") else Path(path)
    return Policy.load(path)


def env_config_of(policy: Policy) -> EnvConfig:
    """The environment config a policy was trained with (stored in its metadata by
    bimacppo-train), so that deployment observes and decodes exactly as training did."""
    raw = policy.meta.get("env_config")
    if raw is None:
        return EnvConfig.load()
    try:
        return EnvConfig.from_dict(raw, where=f"{policy.path} (metadata env_config)")
    except ValueError as exc:
        raise CheckpointError(policy.path, str(exc)) from None


def route_for(road: RoadMap, start: np.ndarray, goal: np.ndarray, world_config: WorldConfig | None = None) -> np.ndarray:
    """The A* reference waypoint set from a start pose to a goal pose on the planner's own map
    copy — the same function the world calls at reset, so both get the same waypoints."""
    return reference_route(road, start[:2], goal[:2], world_config,
                           start_psi=float(start[2]) if len(start) > 2 else None)


class HighLevelPlanner:
    """Policy → x_IMR, one decision per call; see the module docstring."""

    def __init__(self, policy: Policy, road: RoadMap, config: EnvConfig | None = None):
        self.policy = policy
        self.road = road
        self.cfg = config or env_config_of(policy)
        if policy.obs_dim != self.cfg.obs_dim or tuple(policy.nvec) != self.cfg.nvec:
            raise CheckpointError(policy.path, f"policy expects obs_dim={policy.obs_dim}, nvec={policy.nvec}; "
                                                f"the environment config gives {self.cfg.obs_dim}, {self.cfg.nvec}")
        self.tracker: WaypointTracker | None = None
        self.goal: np.ndarray | None = None

    @classmethod
    def load(cls, policy_path: str | Path | None = None, map_id: str = "dual_lane_4way",
             config: EnvConfig | None = None) -> "HighLevelPlanner":
        return cls(load_policy(policy_path), load_map(map_id), config)

    def reset(self, ego: np.ndarray, goal: np.ndarray, route: np.ndarray | None = None) -> None:
        """New episode: plan the A* route from the EV's pose to the goal (or take ``route``)."""
        ego = _finite(ego, 4, "ego state")
        self.goal = _finite(goal, 3, "goal pose")
        if route is None:
            route = route_for(self.road, np.array([ego[0], ego[1], ego[3]]), self.goal)
        self.tracker = WaypointTracker(route, self.cfg.action.n_waypoints)
        self.tracker.update(ego[0], ego[1])

    @property
    def ready(self) -> bool:
        return self.tracker is not None

    def step(self, ego: np.ndarray, svs: np.ndarray) -> tuple[np.ndarray, dict]:
        """One decision: returns x_IMR = [x, y, v, psi] and {action, obs, lane_change, candidates}."""
        if self.tracker is None:
            raise RuntimeError("HighLevelPlanner.step() before reset(): no goal/route yet")
        ego = _finite(ego, 4, "ego state")
        svs = np.asarray(svs, dtype=np.float64).reshape(-1, 4)
        if not np.all(np.isfinite(svs)):
            raise ValueError("SV states contain NaN or inf")
        obs = observe(self.cfg.observation, ego, self.goal, svs)
        self.tracker.update(ego[0], ego[1])
        action = self.policy.act(obs, deterministic=True)
        x_imr, changed = decode_action(action, self.tracker, self.cfg.action, self.road.lateral_point, ego)
        return x_imr, {"action": action, "obs": obs, "lane_change": changed,
                       "candidates": self.tracker.candidates()}


def _finite(a, n: int, what: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64).reshape(-1)
    if a.shape != (n,):
        raise ValueError(f"{what} must have {n} elements, got {a.shape[0]}")
    if not all(math.isfinite(v) for v in a):
        raise ValueError(f"{what} contains NaN or inf: {a.tolist()}")
    return a
