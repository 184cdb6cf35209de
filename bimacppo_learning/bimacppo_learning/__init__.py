"""bimacppo_learning: the training stack of BiM-ACPPO (env, PPO, trainer, evaluation, experiments).

Deployment never imports this package; it imports the planner, world, controller and curriculum
cores, never their ROS nodes.

Importing the package stays cheap (no torch, no gymnasium): it only makes sure the Gymnasium ids
below are registered as soon as gymnasium is imported, so that ``gym.make(ENV_ID)`` and
``gym.make("bimacppo_learning:" + ENV_ID)`` work. An installed package also does that without
this import, through the ``.pth`` file that setup.py writes from ``_gymnasium_hook.py``.
"""

import bimacppo_common  # noqa: F401  (before torch loads: idle OpenMP threads sleep; bimacppo_common says why)

__version__ = "0.1.0"

#: Gymnasium id -> map id of the scenario (``gym.make(id, config=..., mpc_solver=...)``).
MAP_IDS = {
    "bimacppo/DualLaneIntersection-v0": "dual_lane_4way",
    "bimacppo/SingleLaneIntersection-v0": "single_lane_4way",
    "bimacppo/ThreeLaneOvertake-v0": "three_lane_straight",
}

ENV_ENTRY_POINT = "bimacppo_learning.env:IntersectionEnv"


def register_envs() -> None:
    """Register the three scenario ids with Gymnasium (idempotent). The entry point is a string,
    so this imports gymnasium but not the env (or the world, controller and torch behind it)."""
    import gymnasium as gym

    for env_id, map_id in MAP_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=ENV_ENTRY_POINT, kwargs={"map_id": map_id})


from ._gymnasium_hook import install as _install_gymnasium_hook  # noqa: E402

_install_gymnasium_hook()
