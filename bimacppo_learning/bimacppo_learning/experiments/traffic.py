"""Slow traffic for the overtaking experiment (paper §IV-C).

The rules themselves live elsewhere: the curriculum's task folding onto the road's only task in
``batch.py``, the one implementation of the decision step, and how many SVs drive slowly per
scenario seed in ``bimacppo_sim.draw_n_slow`` (the world node draws the same); this module names
the overtaking env the fine-tune trains and tests on.
"""
from __future__ import annotations

from bimacppo_sim import draw_n_slow  # noqa: F401  (re-exported: the overtaking protocol's draw)

from ..vec_env import EnvFactory


def make_overtake_env(map_id: str, env_config, mpc_solver: str, n_slow_max: int) -> EnvFactory:
    """The overtaking env's factory: called, one env; ``make_batch(n)``, the batched vector env.
    Each episode slows ``draw_n_slow(scenario_seed, n_sv, n_slow_max)`` SVs unless its reset
    options give ``n_slow``."""
    return EnvFactory(map_id, env_config, mpc_solver, slow_svs=int(n_slow_max))
