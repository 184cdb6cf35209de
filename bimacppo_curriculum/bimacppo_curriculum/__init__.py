"""bimacppo_curriculum: the BiMAB curriculum (Exp3.S bilevel bandit) and the baseline schedulers.

Core code: numpy + pyyaml only, never rclpy (the ROS node lives in ``ros/``).

    from bimacppo_curriculum import make_scheduler
    s = make_scheduler("bimab", seed=0, total_episodes=5000)
    i, j = s.sample(); s.update(i, j, episode_return)
"""
from __future__ import annotations

from .bandit import BiMAB, RDACPPO, RewardRescaler
from .base import N_TASKS, Scheduler
from .baselines import FixedPPO, ManualCPPO, RandomCPPO
from .config import BiMABConfig, FixedConfig, ManualConfig, RandomConfig, RDConfig

__version__ = "0.1.0"

SCHEDULERS: dict[str, type[Scheduler]] = {
    "bimab": BiMAB,
    "fixed": FixedPPO,
    "random": RandomCPPO,
    "manual": ManualCPPO,
    "rd": RDACPPO,
}


def make_scheduler(name: str, seed: int = 0, total_episodes: int | None = None, config=None) -> Scheduler:
    """Build a scheduler by name.

    config: None (the packaged ``config/<name>.yaml``), a YAML path, a dict of overrides
    applied on top of the packaged file, or the scheduler's config dataclass.
    """
    if name not in SCHEDULERS:
        raise ValueError(f"unknown scheduler {name!r}; choose one of {sorted(SCHEDULERS)}")
    return SCHEDULERS[name](config=config, seed=seed, total_episodes=total_episodes)


def scheduler_from_state(state: dict) -> Scheduler:
    """Rebuild whichever scheduler a state_dict came from (its saved config included)."""
    if not isinstance(state, dict) or state.get("scheduler") not in SCHEDULERS:
        got = state.get("scheduler") if isinstance(state, dict) else type(state).__name__
        raise ValueError(f"state: key 'scheduler' must be one of {sorted(SCHEDULERS)}, got {got!r}")
    cls = SCHEDULERS[state["scheduler"]]
    sched = cls(config=cls.config_cls.from_dict(state.get("config"), source="state: key 'config'"),
                seed=state.get("seed", 0), total_episodes=state.get("total_episodes"))
    sched.load_state_dict(state)
    return sched


__all__ = [
    "BiMAB", "RDACPPO", "FixedPPO", "RandomCPPO", "ManualCPPO", "Scheduler", "RewardRescaler",
    "BiMABConfig", "RDConfig", "ManualConfig", "FixedConfig", "RandomConfig",
    "SCHEDULERS", "make_scheduler", "scheduler_from_state", "N_TASKS",
]
