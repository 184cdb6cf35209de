"""The high-level Gymnasium environment of BiM-ACPPO: world + action decoding + reward + NMPC.

One RL step = the policy picks (A1, A2, A3), that is decoded into the intermediate
reference state x_IMR, and the NMPC tracks x_IMR for ``decision_every`` world ticks.
A curriculum chooses the scenario through ``reset(options={"n_sv": i, "task": j})``.

The step itself is ``batch.IntersectionBatch`` with one slot: training's batched vector env
runs the same code with B slots, so there is one implementation of the decision step.
"""
from __future__ import annotations

import os
from typing import Any, Mapping

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from bimacppo_planner.decision import EnvConfig

from .batch import IntersectionBatch, task_index  # noqa: F401  (task_index: part of this module's API)

from . import MAP_IDS, register_envs  # noqa: F401  (the ids live in the package, importable without this module)


def as_env_config(config: EnvConfig | str | os.PathLike | Mapping | None) -> EnvConfig | None:
    """``config`` as ``gym.make(id, config=...)`` may pass it: an EnvConfig, a YAML path (str or
    Path, ``EnvConfig.load``), a dict in the YAML's layout (``EnvConfig.from_dict``; sections and
    keys left out take EnvConfig's defaults), or None (the packaged config/env.yaml)."""
    if config is None or isinstance(config, EnvConfig):
        return config
    if isinstance(config, (str, os.PathLike)):
        return EnvConfig.load(config)
    if isinstance(config, Mapping):
        return EnvConfig.from_dict(config, where="config")
    raise TypeError(f"config must be an EnvConfig, a YAML path or a dict, got {type(config).__name__}")


class IntersectionEnv(gym.Env):
    """Gymnasium environment; see the module docstring and docs/method.md.

    ``slow_svs`` > 0: each episode slows 0..slow_svs SVs (drawn from the scenario seed) unless
    the reset options say ``n_slow`` (overtaking fine-tune, paper §IV-C)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, map_id: str = "dual_lane_4way", config: EnvConfig | str | os.PathLike | Mapping | None = None,
                 mpc_solver: str = "fast", render_mode: str | None = None,
                 world_config=None, tasks: tuple | None = None, slow_svs: int = 0, mpc_config=None):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        config = as_env_config(config)
        self._core = IntersectionBatch(1, map_id=map_id, config=config, mpc_solver=mpc_solver,
                                       world_config=world_config, tasks=tasks, slow_svs=slow_svs,
                                       mpc_config=mpc_config)
        self.cfg = self._core.cfg
        self.road = self._core.road
        self.world = self._core.worlds[0]
        self.ctrl = self._core.ctrl
        self.render_mode = render_mode
        self.max_sv = self._core.max_sv
        self.tasks = self._core.tasks
        d = self.cfg.obs_dim
        self.observation_space = spaces.Box(low=-np.inf, high=np.inf, shape=(d,), dtype=np.float32)
        self.action_space = spaces.MultiDiscrete(np.array(self.cfg.nvec, dtype=np.int64))
        self._renderer = None

    @property
    def scenario(self):
        return self._core.scenarios[0]

    @property
    def tracker(self):
        return self._core.trackers[0]

    def scenario_from_options(self, options: dict | None):
        """The Scenario that ``reset(options=...)`` would run (draws use this env's np_random)."""
        self._core.rngs[0] = self.np_random
        return self._core.scenario_from_options(0, options)

    # -- gym API ---------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        # the slot draws what the options leave open from this env's np_random (seeded above)
        self._core.rngs[0] = self.np_random
        return self._core.reset(0, None, options)

    def step(self, action):
        if not self._core.running[0]:
            raise RuntimeError("call reset() before step()" if self.scenario is None else
                               "episode is over: call reset() before step()")
        action = np.asarray(action).reshape(1, -1)
        obs, rew, term, trunc, infos = self._core.step(action)
        return obs[0], float(rew[0]), bool(term[0]), bool(trunc[0]), infos[0]

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            from bimacppo_sim.render import Renderer

            self._renderer = Renderer(self.world)
        cands = None if self.tracker is None else self.tracker.candidates()
        x_imr = self._core.x_imr[0]
        return self._renderer.rgb_array(x_imr=None if np.isnan(x_imr[0]) else x_imr, candidates=cands)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close()
