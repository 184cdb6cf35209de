"""B high-level episodes stepped together: the one implementation of a BiM-ACPPO decision step.

One decision = the policy's (A1, A2, A3) per episode is decoded into x_IMR (``decision.py``, the
planner node's own code), then ``decision_every`` world ticks run in which *one* batched NMPC call
(``solve_batch``, a numba kernel parallel over the problems) computes every episode's command, and
each world steps with its own. Rewards (eq. 26-28) and observations (eq. 18-20) come from the
shared ``decision.py`` functions.

The Gymnasium env (``env.IntersectionEnv``) is this class with B = 1, and the training vector env
(``vec_env.BatchedVectorEnv``) is this class with B = num_envs, so the single-env path and the
batched path cannot drift apart: a batch reproduces, slot by slot, the trajectories of B separate
single envs with the same seeds and actions (tests/test_learning_batch.py).

Worlds are stepped one after another: the SV model is branchy per-vehicle logic (reservations,
gap acceptance) that gains little from arrays; the NMPC, which dominated the per-tick cost, and
the policy forward are the batched parts.

Episode options (``reset(i, seed, options)``): ``n_sv``, ``task`` (index or name), optional
``scenario_seed`` and ``n_slow``; what is not given is drawn from the slot's generator, seeded by
``seed`` exactly as Gymnasium seeds ``env.np_random``. On a map with a single task (the straight
road) every task folds onto it, so a curriculum's three task arms all run; with ``slow_svs`` > 0
each episode gets ``draw_n_slow(seed, n_sv, slow_svs)`` slow SVs (overtaking fine-tune, §IV-C).
"""
from __future__ import annotations

import time
from typing import Any, Mapping

import numpy as np
from gymnasium.utils import seeding

from bimacppo_common.conventions import TASKS, task_on_map
from bimacppo_mpc import MPCConfig, make_controller
from bimacppo_planner.decision import EnvConfig, WaypointTracker, decode_action, idle_share, observe, step_reward
from bimacppo_sim import Scenario, World, draw_n_slow, load_map
from bimacppo_sim.config import DriverConfig
from bimacppo_sim.drivers import (closing_on_lead, junction_distance, junction_threatened, lanes_to_free_lane,
                                  queued_behind_lead)

RESET_OPTIONS = ("n_sv", "task", "scenario_seed", "n_slow")
SEED_HIGH = 2 ** 31 - 1


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


class IntersectionBatch:
    """B episodes on one map, stepped together; see the module docstring."""

    def __init__(self, num_envs: int, map_id: str = "dual_lane_4way", config: EnvConfig | None = None,
                 mpc_solver: str = "fast", world_config=None, tasks: tuple | None = None,
                 slow_svs: int = 0, mpc_config: MPCConfig | None = None):
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if isinstance(slow_svs, bool) or not isinstance(slow_svs, (int, np.integer)) or slow_svs < 0:
            raise ValueError(f"slow_svs must be an integer >= 0, got {slow_svs!r}")
        self.B = int(num_envs)
        self.cfg = config or EnvConfig.load()
        self.road = load_map(map_id)
        self.worlds = [World(self.road, world_config) for _ in range(self.B)]
        self.ctrl = make_controller(mpc_config or MPCConfig.load(), solver=mpc_solver)
        self.max_sv_map = int(self.worlds[0].max_sv)
        self.max_sv = min(self.cfg.observation.max_sv, self.max_sv_map)
        self.tasks = tuple(tasks) if tasks is not None else self.road.tasks
        self.slow_svs = int(slow_svs)
        self.obs_dim = self.cfg.obs_dim
        self.nvec = self.cfg.nvec
        B = self.B
        self.rngs: list[np.random.Generator] = [seeding.np_random(None)[0] for _ in range(B)]
        self.scenarios: list[Scenario | None] = [None] * B
        self.trackers: list[WaypointTracker | None] = [None] * B
        self.u_prev = np.zeros((B, 2))
        self.x_imr = np.full((B, 4), np.nan)
        self.returns = np.zeros(B)
        self.steps = np.zeros(B, np.int64)
        self.lane_changes = np.zeros(B, np.int64)
        self.mpc_failures = np.zeros(B, np.int64)
        self.running = np.zeros(B, bool)      # reset and not yet finished
        # whether the EV entered the junction box while it was threatened: the yield rule's threat
        # test on the true world state (reported per episode; the reward.threat_entry shaping term
        # pays on it). The box edge, not the stop line: the yield rule itself stops with its
        # bumper at or just over the line and enters only when clear. It happens once per episode.
        self._threat_cfg = DriverConfig.load()
        self.crossed = np.zeros(B, bool)       # EV front inside the junction box
        self.threat_entries = np.zeros(B, bool)   # ... and it entered while the junction was threatened
        self.free_lanes: list[int | None] = [None] * B   # lanes_to_free_lane now (reward.free_lane only)
        self._X0 = np.zeros((B, 4))
        # the NMPC's share of the work, where training time goes: seconds in solve_batch, problems
        # solved, SQP iterations over them and problems that ran the second start
        # seconds: wall time in solve_batch; cpu_seconds: this process's CPU time (every thread of the
        # parallel batch) in it, which says what the NMPC costs the machine, not only the loop
        self.mpc_stats = {"seconds": 0.0, "cpu_seconds": 0.0, "problems": 0, "iterations": 0, "second_starts": 0}

    # ----------------------------------------------------------------- episodes
    def scenario_from_options(self, i: int, options: Mapping[str, Any] | None) -> Scenario:
        options = dict(options or {})
        unknown = set(options) - set(RESET_OPTIONS)
        if unknown:
            raise ValueError(f"unknown reset option(s) {sorted(unknown)}; expected {', '.join(RESET_OPTIONS)}")
        rng = self.rngs[i]
        n_sv = options.get("n_sv")
        n_sv = int(rng.integers(0, self.max_sv + 1)) if n_sv is None else int(n_sv)
        if not 0 <= n_sv <= self.max_sv_map:
            raise ValueError(f"n_sv={n_sv} impossible on map {self.road.id!r} (0..{self.max_sv_map})")
        task = options.get("task")
        if task is None:
            task = self.tasks[int(rng.integers(0, len(self.tasks)))]
        else:
            task = task_on_map(TASKS[task_index(task)], self.tasks)
        seed = options.get("scenario_seed")
        seed = int(rng.integers(0, SEED_HIGH)) if seed is None else int(seed)
        if "n_slow" not in options:
            if self.slow_svs == 0:
                return Scenario(n_sv=n_sv, task=task, seed=seed)
            return Scenario(n_sv=n_sv, task=task, seed=seed, n_slow=draw_n_slow(seed, n_sv, self.slow_svs))
        n_slow = options["n_slow"]
        if n_slow is not None:
            if isinstance(n_slow, bool) or not isinstance(n_slow, (int, np.integer)):
                raise ValueError(f"reset option n_slow must be None or an integer, got {n_slow!r}")
            if not 0 <= n_slow <= n_sv:
                raise ValueError(f"reset option n_slow={n_slow} out of range 0..n_sv={n_sv}")
            n_slow = int(n_slow)
        return Scenario(n_sv=n_sv, task=task, seed=seed, n_slow=n_slow)

    def reset(self, i: int, seed: int | None = None, options: Mapping[str, Any] | None = None
              ) -> tuple[np.ndarray, dict]:
        """Start a new episode in slot ``i``; returns its observation and info."""
        if seed is not None:
            self.rngs[i] = seeding.np_random(int(seed))[0]
        scenario = self.scenario_from_options(i, options)
        w = self.worlds[i]
        w.reset(scenario)
        self.scenarios[i] = scenario
        tr = WaypointTracker.for_action(w.route, self.cfg.action)
        ego = w.ego_tuple()
        tr.update(ego[0], ego[1])
        self.trackers[i] = tr
        self.ctrl.reset(slots=[i])
        self.u_prev[i] = 0.0
        self.x_imr[i] = np.nan
        self.returns[i] = 0.0
        self.steps[i] = 0
        self.lane_changes[i] = 0
        self.mpc_failures[i] = 0
        self.crossed[i] = False
        self.threat_entries[i] = False
        self.free_lanes[i] = self._free_lanes(i)
        self.running[i] = True
        info = {"n_sv": scenario.n_sv, "task": task_index(scenario.task), "scenario_seed": scenario.seed,
                "n_pcp": int(w.n_pcp)}
        return self.observe(i), info

    def _free_lanes(self, i: int) -> int | None:
        """``lanes_to_free_lane`` of slot i's world for the lane-progress term (None when it is off)."""
        rcfg = self.cfg.reward
        if rcfg.free_lane == 0.0:
            return None
        return lanes_to_free_lane(self.worlds[i], rcfg.go_speed, self.cfg.observation.sv_clip)

    def observe(self, i: int) -> np.ndarray:
        w = self.worlds[i]
        return observe(self.cfg.observation, w.ego, w.goal, w.sv_states(), self.road)

    # --------------------------------------------------------------------- step
    def step(self, actions) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[dict]]:
        """One decision for every slot (all must be running).

        Returns obs (B, obs_dim) float32, rewards (B,), terminated (B,), truncated (B,) and one
        info dict per slot (always: ``x_imr``, ``lane_change`` and ``commands``, the [a, δ] applied
        at each tick of this decision, shape (decision_every, 2) with NaN rows for the ticks after
        the episode ended: a fixed shape, so Gymnasium's vector envs can stack it across envs;
        the episode summary when it ended)."""
        actions = np.asarray(actions)
        if actions.shape != (self.B, len(self.nvec)):
            raise ValueError(f"actions must have shape ({self.B}, {len(self.nvec)}), got {actions.shape}")
        if not self.running.all():
            idle = np.nonzero(~self.running)[0].tolist()
            raise RuntimeError(f"slot(s) {idle} need reset() before step()")
        acfg = self.cfg.action
        changed = np.zeros(self.B, bool)
        for i in range(self.B):
            ego = self.worlds[i].ego_tuple()
            tr = self.trackers[i]
            tr.update(ego[0], ego[1])
            self.x_imr[i], changed[i] = decode_action(actions[i], tr, acfg, self.road.lateral_point, ego,
                                                                self.road.drivable)
        results: list = [None] * self.B
        alive = np.ones(self.B, bool)
        X0 = self._X0
        applied = np.full((acfg.decision_every, self.B, 2), np.nan)   # commands the worlds got, per tick
        ticks = np.zeros(self.B, np.int64)
        rcfg = self.cfg.reward
        shaping = np.zeros(self.B)
        tcfg = self._threat_cfg
        for k in range(acfg.decision_every):
            for i in range(self.B):
                X0[i] = self.worlds[i].ego_tuple()
            cpu0 = time.process_time()
            sol = self.ctrl.solve_batch(X0, self.x_imr, self.u_prev)
            st = self.mpc_stats
            st["seconds"] += sol.solve_time_s
            st["cpu_seconds"] += time.process_time() - cpu0
            st["problems"] += self.B
            st["iterations"] += int(sol.iterations.sum())
            st["second_starts"] += int((sol.starts == 2).sum())
            for i in np.nonzero(alive)[0]:
                if not sol.ok[i]:
                    self.mpc_failures[i] += 1
                threatened = False
                if not self.crossed[i]:
                    threatened = junction_threatened(self.worlds[i], tcfg)
                if rcfg.idle_clear != 0.0 and not threatened and not (
                        rcfg.idle_queue_gap is not None and queued_behind_lead(self.worlds[i], rcfg.idle_queue_gap)):
                    shaping[i] += rcfg.idle_clear * idle_share(rcfg, X0[i, 2]) / acfg.decision_every
                if rcfg.threat_speed != 0.0 and threatened and X0[i, 2] > rcfg.idle_speed and \
                        X0[i, 2] ** 2 > 2.0 * tcfg.stop_decel * max(junction_distance(self.worlds[i]), 0.0):
                    shaping[i] += rcfg.threat_speed / acfg.decision_every
                if rcfg.headway != 0.0 and closing_on_lead(self.worlds[i], tcfg):
                    shaping[i] += rcfg.headway / acfg.decision_every
                res = self.worlds[i].step(sol.u[i])
                if not self.crossed[i] and junction_distance(self.worlds[i]) <= 0.0:
                    self.crossed[i] = True
                    if threatened:        # the state the crossing tick was commanded from
                        self.threat_entries[i] = True
                        shaping[i] += rcfg.threat_entry
                self.u_prev[i] = sol.u[i]
                applied[k, i] = sol.u[i]
                ticks[i] += 1
                results[i] = res
                if res.done:
                    alive[i] = False
            if not alive.any():
                break
        if rcfg.free_lane != 0.0:
            for i in range(self.B):     # the count after the last decision is this one's start
                before, self.free_lanes[i] = self.free_lanes[i], self._free_lanes(i)
                if before is not None and self.free_lanes[i] is not None:
                    shaping[i] += rcfg.free_lane * (self.free_lanes[i] - before)
        obs = np.empty((self.B, self.obs_dim), np.float32)
        rew = np.empty(self.B)
        term = np.zeros(self.B, bool)
        trunc = np.zeros(self.B, bool)
        infos: list[dict] = []
        for i in range(self.B):
            w, res, sc = self.worlds[i], results[i], self.scenarios[i]
            self.steps[i] += 1
            self.lane_changes[i] += int(changed[i])
            outcome = res.outcome if res.done else None
            rew[i] = step_reward(rcfg, bool(changed[i]), outcome, sc.n_sv, int(w.n_pcp),
                                 float(w.ego_tuple()[2]), float(w.dist_to_goal())) + shaping[i]
            self.returns[i] += rew[i]
            info: dict[str, Any] = {"x_imr": self.x_imr[i].copy(), "lane_change": bool(changed[i]),
                                    "commands": applied[:, i].copy()}
            if res.done:
                term[i] = outcome in ("success", "collision") or (outcome == "timeout" and rcfg.timeout_terminal)
                trunc[i] = not term[i]
                self.running[i] = False
                info.update(outcome=outcome, collided_with=res.collided_with, n_sv=sc.n_sv, task=task_index(sc.task), scenario_seed=sc.seed,
                            n_pcp=int(w.n_pcp), episode_return=float(self.returns[i]),
                            episode_steps=int(self.steps[i]), lane_changes=int(self.lane_changes[i]),
                            mpc_failures=int(self.mpc_failures[i]), sim_time=float(w.time),
                            threat_entry=bool(self.threat_entries[i]),
                            episode_ticks=int(w.steps))
            obs[i] = self.observe(i)
            infos.append(info)
        return obs, rew, term, trunc, infos
