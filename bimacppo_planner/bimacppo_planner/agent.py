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
from bimacppo_sim.world import reference_route, resample_route, route_end

from .policy import DEPLOYED_SELECTIONS, CheckpointError, Policy
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
    """The A* reference waypoint set from a start pose [x, y, psi] to a goal pose on the
    planner's own map copy: the function the world calls at reset (``reference_route``), so
    both get the same waypoints, plus two fallbacks for a planner that first sees an episode
    late (restarted, resynchronised, or its goal delivered after the EV moved on), so that it
    plans instead of refusing every tick:

    * a start inside the junction (no straight lane under the EV): the route through the
      junction that passes nearest the EV (heading within 60 deg), from that point on;
    * a start in a lane that can no longer reach the goal under the no-lane-change zone:
      a lane change right up to the junction, else from the adjacent lane.

    ValueError (the strict route's) when neither applies."""
    cfg = world_config or WorldConfig.load()
    try:
        return reference_route(road, start[:2], goal[:2], cfg)
    except ValueError:
        g = road.locate(float(goal[0]), float(goal[1]))
        s = road.locate(float(start[0]), float(start[1]))
        route = None
        if g is not None and s is None:
            route = _route_from_junction(road, start[:2], float(start[2]) if len(start) > 2 else None, g, cfg)
        elif g is not None:
            pts = _late_route(road, start[:2], s, g[0], route_end(road, g, cfg))
            route = None if pts is None else resample_route(pts, cfg.waypoint_spacing)
        if route is None:
            raise
        return route


def _late_route(road: RoadMap, start_xy, start, goal_lane: str, s_end: float):
    """A planner that first sees an episode late (restarted, or its goal delivered after
    the EV moved on) may find the EV in a lane that can no longer reach the goal under the
    no-lane-change zone. Recover rather than stall: first allow a lane change right up to
    the junction, then start from the adjacent lane at the same station (the first
    waypoint is then one lane over, a lane-change length ahead, or at the stop line if that
    is nearer: the MPC steers across). None if neither reaches."""
    ln = road.lanes[start[0]]
    for lid in (start[0], ln.left, ln.right):
        if lid is None:
            continue
        s0 = start[1] if lid == start[0] else min(start[1] + road.cfg.lane_change_length, road.lanes[lid].length)
        try:
            pts, _, _ = road.plan_route(lid, s0, goal_lane, s_end, no_lane_change_zone=0.0)
        except ValueError:
            continue
        return pts if lid == start[0] else np.vstack([np.asarray(start_xy, float)[None, :2], pts])
    return None


def _route_from_junction(road: RoadMap, start_xy, start_psi, goal, cfg):
    """Route for a start inside the junction box: among the routes from each incoming lane's
    stop line to the goal, the one nearest the start (within a lane width, heading within
    60 deg when known), from its nearest waypoint on; None if no route passes close."""
    if road.kind != "four_way" or not road.drivable(float(start_xy[0]), float(start_xy[1])):
        return None
    p = np.array([float(start_xy[0]), float(start_xy[1])])
    s_end = route_end(road, goal, cfg)
    best = None
    for lid, ln in road.lanes.items():
        if ln.kind != "in":
            continue
        try:
            pts, _, _ = road.plan_route(lid, ln.length, goal[0], s_end)
        except ValueError:
            continue
        fine = resample_route(pts, 0.5)
        d = np.hypot(fine[:, 0] - p[0], fine[:, 1] - p[1])
        if start_psi is not None:   # a connector crossing this one at the start point heads elsewhere
            turn = np.abs(np.angle(np.exp(1j * (fine[:, 2] - float(start_psi)))))
            d = np.where(turn <= math.radians(60.0), d, np.inf)
        i = int(np.argmin(d))
        if d[i] <= road.lane_width and (best is None or d[i] < best[0]):
            best = (float(d[i]), pts, fine[i, :2], 0.5 * i)
    if best is None:
        return None
    _, pts, near, s_near = best
    # the polyline from the nearest point on (its arc length on the 0.5 m resampling)
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    tail = np.vstack([near[None, :], pts[cum > s_near + 1e-6]])
    return resample_route(tail, cfg.waypoint_spacing)


def observed_goal(road: RoadMap, goal: np.ndarray, ego_xy, world_config: WorldConfig | None = None) -> np.ndarray:
    """The goal pose the policy observes, given the source's goal pose [x, y, psi].

    The observation (Eq. 18-20) locates the EV only relative to its goal, so the goal's
    distance from the junction is, for the policy, where the junction is. Training puts
    every goal ``success_distance`` past the junction exit; another source may put it
    anywhere along the exit lane (40 m out, say). Rule, on a four-way map with the goal on
    an exit lane: the policy observes the point on the goal's lane ``success_distance`` past
    the exit; once the EV is on an exit lane of the goal's arm it observes the point
    ``success_distance`` ahead of the EV, never beyond the source's goal. The source's own
    goal still decides the route, the task and success. Any goal our world draws lies
    exactly at ``success_distance``, where the rule is the identity, so training and
    deployment observe the same; a goal off the exit lanes or on a straight road is
    observed as it is."""
    goal = np.asarray(goal, dtype=np.float64)
    if road.kind != "four_way":
        return goal
    g = road.locate(float(goal[0]), float(goal[1]))
    if g is None or road.lanes[g[0]].kind != "out":
        return goal
    d = (world_config or WorldConfig.load()).success_distance
    s_obs = d
    e = road.locate(float(ego_xy[0]), float(ego_xy[1]))
    if e is not None and road.lanes[e[0]].kind == "out" and road.lanes[e[0]].arm == road.lanes[g[0]].arm:
        s_obs = max(d, e[1] + d)
    s_obs = min(s_obs, max(g[1], d), road.lanes[g[0]].length)
    if abs(s_obs - g[1]) < 1e-9:
        return goal
    x, y, _ = road.lane_point(g[0], s_obs)
    return np.array([x, y, goal[2]])


class HighLevelPlanner:
    """Policy → x_IMR, one decision per call; see the module docstring."""

    #: how the deployed planner picks each head's action: deterministic choices only, so that the
    #: same inputs give the same reference (``bimacppo_planner.policy.head_median`` says why the
    #: median exists beside the argmax)
    SELECTIONS = DEPLOYED_SELECTIONS

    def __init__(self, policy: Policy, road: RoadMap, config: EnvConfig | None = None,
                 action_selection: str | None = None):
        """``action_selection`` None (or "") runs the policy the way its file says (``Policy.selection``)."""
        action_selection = action_selection or policy.selection
        if action_selection not in self.SELECTIONS:
            raise ValueError(f"action_selection must be one of {self.SELECTIONS}, got {action_selection!r}")
        self.policy = policy
        self.action_selection = action_selection
        self._act = policy.act_median if action_selection == "median" else policy.act
        self.road = road
        self.cfg = config or env_config_of(policy)
        if policy.obs_dim != self.cfg.obs_dim or tuple(policy.nvec) != self.cfg.nvec:
            raise CheckpointError(policy.path, f"policy expects obs_dim={policy.obs_dim}, nvec={policy.nvec}; "
                                                f"the environment config gives {self.cfg.obs_dim}, {self.cfg.nvec}")
        self.tracker: WaypointTracker | None = None
        self.goal: np.ndarray | None = None
        self.world_cfg = WorldConfig.load()   # the rules the routes and the observed goal follow

    @classmethod
    def load(cls, policy_path: str | Path | None = None, map_id: str = "dual_lane_4way",
             config: EnvConfig | None = None, action_selection: str | None = None) -> "HighLevelPlanner":
        return cls(load_policy(policy_path), load_map(map_id), config, action_selection)

    def reset(self, ego: np.ndarray, goal: np.ndarray, route: np.ndarray | None = None) -> None:
        """New episode: plan the A* route from the EV's pose to the goal (or take ``route``)."""
        ego = _finite(ego, 4, "ego state")
        self.goal = _finite(goal, 3, "goal pose")
        if route is None:
            route = route_for(self.road, np.array([ego[0], ego[1], ego[3]]), self.goal)
        self.tracker = WaypointTracker.for_action(route, self.cfg.action)
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
        obs = observe(self.cfg.observation, ego, observed_goal(self.road, self.goal, ego[:2], self.world_cfg), svs,
                      self.road)
        self.tracker.update(ego[0], ego[1])
        action = self._act(obs)
        x_imr, changed = decode_action(action, self.tracker, self.cfg.action, self.road.lateral_point, ego,
                                          self.road.drivable)
        return x_imr, {"action": action, "obs": obs, "lane_change": changed,
                       "candidates": self.tracker.candidates()}


def _finite(a, n: int, what: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64).reshape(-1)
    if a.shape != (n,):
        raise ValueError(f"{what} must have {n} elements, got {a.shape[0]}")
    if not all(math.isfinite(v) for v in a):
        raise ValueError(f"{what} contains NaN or inf: {a.tolist()}")
    return a
