"""The high-level Gymnasium environment of BiM-ACPPO: world + action decoding + reward + NMPC.

One RL step = the policy picks (A1, A2, A3), that is decoded into the intermediate
reference state x_IMR, and the NMPC tracks x_IMR for ``decision_every`` world ticks.
A curriculum chooses the scenario through ``reset(options={"n_sv": i, "task": j})``.
"""
from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from bimacppo_mpc import MPCConfig, make_controller
from bimacppo_sim import TASKS, Scenario, World, load_map

from bimacppo_planner.decision import EnvConfig, WaypointTracker, decode_action, observe, step_reward

MAP_IDS = {
    "bimacppo/DualLaneIntersection-v0": "dual_lane_4way",
    "bimacppo/SingleLaneIntersection-v0": "single_lane_4way",
    "bimacppo/ThreeLaneOvertake-v0": "three_lane_straight",
}


def task_index(task) -> int:
    """Accept 0/1/2 or 'left'/'straight'/'right' (paper: j = 0, 1, 2)."""
    if isinstance(task, str):
        if task not in TASKS:
            raise ValueError(f"unknown task {task!r}; expected one of {TASKS}")
        return TASKS.index(task)
    j = int(task)
    if not 0 <= j < len(TASKS):
        raise ValueError(f"task index {task!r} out of range 0..{len(TASKS) - 1}")
    return j


class IntersectionEnv(gym.Env):
    """Gymnasium environment; see the module docstring and docs/method.md."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, map_id: str = "dual_lane_4way", config: EnvConfig | None = None,
                 mpc_solver: str = "fast", render_mode: str | None = None,
                 world_config=None, tasks: tuple | None = None):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.cfg = config or EnvConfig.load()
        self.road = load_map(map_id)
        self.world = World(self.road, world_config)
        self.ctrl = make_controller(MPCConfig.load(), solver=mpc_solver)
        self.render_mode = render_mode
        self.max_sv = min(self.cfg.observation.max_sv, int(self.world.max_sv))
        self.tasks = tuple(tasks) if tasks is not None else tuple(t for t in TASKS if t in self.road.turns)
        d = self.cfg.obs_dim
        self.observation_space = spaces.Box(low=-np.inf, high=np.inf, shape=(d,), dtype=np.float32)
        self.action_space = spaces.MultiDiscrete(np.array(self.cfg.nvec, dtype=np.int64))
        self.tracker: WaypointTracker | None = None
        self._u_prev = np.zeros(2)
        self._x_imr = None
        self._ret = 0.0
        self._steps = 0
        self._lane_changes = 0
        self._mpc_failures = 0
        self._renderer = None

    # -- helpers ---------------------------------------------------------------------
    def _obs(self) -> np.ndarray:
        return observe(self.cfg.observation, self.world.ego, self.world.goal, self.world.sv_states())

    def scenario_from_options(self, options: dict | None) -> Scenario:
        """``n_slow`` (optional): how many SVs drive slowly (overtaking fine-tuning, paper §IV-C);
        an int in 0..n_sv, or None to let the world draw it uniformly in 0..n_sv; absent keeps
        the Scenario default (no slow SV), so the intersection protocol is unchanged."""
        options = dict(options or {})
        unknown = set(options) - {"n_sv", "task", "scenario_seed", "n_slow"}
        if unknown:
            raise ValueError(f"unknown reset option(s) {sorted(unknown)}; expected n_sv, task, scenario_seed, n_slow")
        rng = self.np_random
        n_sv = options.get("n_sv")
        n_sv = int(rng.integers(0, self.max_sv + 1)) if n_sv is None else int(n_sv)
        if not 0 <= n_sv <= self.world.max_sv:
            raise ValueError(f"n_sv={n_sv} impossible on map {self.road.id!r} (0..{self.world.max_sv})")
        task = options.get("task")
        task = self.tasks[int(rng.integers(0, len(self.tasks)))] if task is None else TASKS[task_index(task)]
        seed = options.get("scenario_seed")
        seed = int(rng.integers(0, 2**31 - 1)) if seed is None else int(seed)
        if "n_slow" not in options:
            return Scenario(n_sv=n_sv, task=task, seed=seed)
        n_slow = options["n_slow"]
        if n_slow is not None:
            if isinstance(n_slow, bool) or not isinstance(n_slow, (int, np.integer)):
                raise ValueError(f"reset option n_slow must be None or an integer, got {n_slow!r}")
            if not 0 <= n_slow <= n_sv:
                raise ValueError(f"reset option n_slow={n_slow} out of range 0..n_sv={n_sv}")
            n_slow = int(n_slow)
        return Scenario(n_sv=n_sv, task=task, seed=seed, n_slow=n_slow)

    # -- gym API ---------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        scenario = self.scenario_from_options(options)
        self.world.reset(scenario)
        self.scenario = scenario
        self.tracker = WaypointTracker(self.world.route, self.cfg.action.n_waypoints)
        self.tracker.update(self.world.ego[0], self.world.ego[1])
        self.ctrl.reset()
        self._u_prev = np.zeros(2)
        self._x_imr = None
        self._ret = 0.0
        self._steps = 0
        self._lane_changes = 0
        self._mpc_failures = 0
        info = {"n_sv": scenario.n_sv, "task": task_index(scenario.task), "scenario_seed": scenario.seed,
                "n_pcp": int(self.world.n_pcp)}
        return self._obs(), info

    def step(self, action):
        if self.tracker is None:
            raise RuntimeError("call reset() before step()")
        ego = self.world.ego
        self.tracker.update(ego[0], ego[1])
        x_imr, changed = decode_action(action, self.tracker, self.cfg.action, self.road.lateral_point)
        self._x_imr = x_imr
        res = None
        for _ in range(self.cfg.action.decision_every):
            sol = self.ctrl.solve(self.world.ego, x_imr, self._u_prev)
            if not sol.ok:
                self._mpc_failures += 1
            res = self.world.step(sol.u)
            self._u_prev = np.asarray(sol.u, dtype=np.float64)
            if res.done:
                break
        self._steps += 1
        self._lane_changes += int(changed)
        terminated = truncated = False
        info: dict[str, Any] = {"x_imr": x_imr}
        outcome = res.outcome if res.done else None
        reward = step_reward(self.cfg.reward, changed, outcome, self.scenario.n_sv, int(self.world.n_pcp),
                             float(self.world.ego[2]), float(self.world.dist_to_goal()))
        if res.done:
            terminated = outcome in ("success", "collision")
            truncated = outcome == "timeout"
        self._ret += reward
        if res.done:
            info.update(outcome=res.outcome, n_sv=self.scenario.n_sv, task=task_index(self.scenario.task),
                        scenario_seed=self.scenario.seed, n_pcp=int(self.world.n_pcp),
                        episode_return=self._ret, episode_steps=self._steps,
                        lane_changes=self._lane_changes, mpc_failures=self._mpc_failures,
                        sim_time=float(self.world.time))
        return self._obs(), float(reward), terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            from bimacppo_sim.render import Renderer

            self._renderer = Renderer(self.world)
        cands = None if self.tracker is None else self.tracker.candidates()
        return self._renderer.rgb_array(x_imr=self._x_imr, candidates=cands)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close()


def register_envs() -> None:
    """Register the three scenario ids with Gymnasium (idempotent)."""
    for env_id, map_id in MAP_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="bimacppo_learning.env:IntersectionEnv",
                         kwargs={"map_id": map_id})
