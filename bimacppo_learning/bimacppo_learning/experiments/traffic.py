"""Slow traffic for the overtaking experiment (paper §IV-C): a Gymnasium wrapper and the seeded
draw of how many SVs drive slowly, shared by the fine-tune and its tests."""
from __future__ import annotations

import gymnasium as gym
import numpy as np

from bimacppo_sim import TASKS


def slow_rng(seed: int) -> np.random.Generator:
    """A stream of its own per scenario seed (a SeedSequence child), independent of the world's."""
    return np.random.default_rng(np.random.SeedSequence(int(seed)).spawn(1)[0])


def draw_n_slow(seed: int, n_sv: int, n_slow_max: int) -> int:
    """How many SVs drive slowly: uniform in 0..min(n_sv, n_slow_max), a function of the seed."""
    return int(slow_rng(seed).integers(0, min(int(n_sv), n_slow_max) + 1))


class SlowTraffic(gym.Wrapper):
    """Overtaking episodes: the curriculum's task folds onto the road's only task, and each
    reset gets ``n_slow`` slow SVs (the env's reset option) drawn from the reset seed, because
    the trainer passes only ``n_sv`` and ``task``."""

    def __init__(self, env, n_slow_max: int):
        super().__init__(env)
        self.n_slow_max = int(n_slow_max)
        self._rng = np.random.default_rng()

    def reset(self, *, seed=None, options=None):
        from ..env import task_index

        base = self.env.unwrapped
        opts = dict(options or {})
        if opts.get("task") is not None and len(base.tasks) == 1 and TASKS[task_index(opts["task"])] not in base.tasks:
            opts["task"] = base.tasks[0]
        if "n_slow" not in opts:
            rng = slow_rng(seed) if seed is not None else self._rng
            if opts.get("n_sv") is None:
                opts["n_sv"] = int(rng.integers(0, base.max_sv + 1))
            opts["n_slow"] = int(rng.integers(0, min(int(opts["n_sv"]), self.n_slow_max) + 1))
        return self.env.reset(seed=seed, options=opts)


def make_overtake_env(map_id: str, env_config, mpc_solver: str, n_slow_max: int):
    """Picklable factory (async vector env workers) of the wrapped overtaking env."""
    from ..env import IntersectionEnv

    return SlowTraffic(IntersectionEnv(map_id=map_id, config=env_config, mpc_solver=mpc_solver), n_slow_max)
