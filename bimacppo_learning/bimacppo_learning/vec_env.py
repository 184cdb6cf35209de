"""The training vector env: B episodes in one process, stepped as one batch.

``BatchedVectorEnv`` is a Gymnasium ``VectorEnv`` over ``batch.IntersectionBatch`` with autoreset
disabled, so the trainer drives it exactly like the subprocess ``AsyncVectorEnv`` (it resets each
finished slot itself, with the curriculum's next scenario, through ``options["reset_mask"]``).
Compared with one subprocess per env it pays no pickling or inter-process hand-off per step, runs
one NMPC call and one policy forward for all B, and lets numba spread the NMPC over the cores.

``EnvFactory`` is the picklable description of the training env (map, env config, solver, slow
SVs): called, it builds one Gymnasium env (for the async/sync vector envs and evaluation);
``make_batch(n)`` builds the batched vector env.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv

from bimacppo_planner.decision import EnvConfig

from .batch import IntersectionBatch


class BatchedVectorEnv(VectorEnv):
    """See the module docstring. Infos carry the episode summary (``outcome``, ``episode_return``,
    ...) of the slots whose episode ended on that step, with Gymnasium's ``_key`` masks."""

    metadata = {"autoreset_mode": AutoresetMode.DISABLED}

    def __init__(self, num_envs: int, **batch_kwargs: Any):
        self.batch = IntersectionBatch(num_envs, **batch_kwargs)
        self.num_envs = self.batch.B
        d = self.batch.obs_dim
        self.single_observation_space = spaces.Box(low=-np.inf, high=np.inf, shape=(d,), dtype=np.float32)
        self.single_action_space = spaces.MultiDiscrete(np.array(self.batch.nvec, dtype=np.int64))
        self.observation_space = spaces.Box(low=-np.inf, high=np.inf, shape=(self.num_envs, d), dtype=np.float32)
        self.action_space = spaces.MultiDiscrete(np.tile(self.single_action_space.nvec, (self.num_envs, 1)))
        self._obs = np.zeros((self.num_envs, d), np.float32)

    def reset(self, *, seed=None, options=None):
        """Reset the slots in ``options["reset_mask"]`` (default: all), each with its seed from
        ``seed`` (an int seeds slot k with seed + k, a list gives one per slot)."""
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        mask = np.ones(self.num_envs, bool) if mask is None else np.asarray(mask, bool)
        if mask.shape != (self.num_envs,):
            raise ValueError(f"reset_mask must have shape ({self.num_envs},), got {mask.shape}")
        if seed is None or isinstance(seed, (int, np.integer)):
            seeds = [None if seed is None else int(seed) + k for k in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"need {self.num_envs} seeds, got {len(seeds)}")
        infos: dict = {}
        for i in np.nonzero(mask)[0]:
            self._obs[i], info = self.batch.reset(int(i), seeds[i], options)
            infos = self._add_info(infos, info, int(i))
        return self._obs.copy(), infos

    def step(self, actions):
        obs, rew, term, trunc, per_slot = self.batch.step(actions)
        self._obs[:] = obs
        infos: dict = {}
        for i in np.nonzero(term | trunc)[0]:
            summary = {k: v for k, v in per_slot[i].items() if k != "x_imr"}
            infos = self._add_info(infos, summary, int(i))
        return obs, rew, term, trunc, infos

    def close_extras(self, **kwargs):
        pass


@dataclass(frozen=True)
class EnvFactory:
    """Picklable recipe of the training env; ``factory()`` = one env, ``make_batch(n)`` = n batched."""

    map_id: str = "dual_lane_4way"
    env_config: EnvConfig | None = None
    mpc_solver: str = "fast"
    slow_svs: int = 0

    def __call__(self):
        from .env import IntersectionEnv

        return IntersectionEnv(map_id=self.map_id, config=self.env_config, mpc_solver=self.mpc_solver,
                               slow_svs=self.slow_svs)

    def make_batch(self, num_envs: int) -> BatchedVectorEnv:
        return BatchedVectorEnv(num_envs, map_id=self.map_id, config=self.env_config,
                                mpc_solver=self.mpc_solver, slow_svs=self.slow_svs)
