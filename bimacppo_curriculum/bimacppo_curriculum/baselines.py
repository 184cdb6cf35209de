"""The paper's baseline schedulers (§IV-A), behind the same interface as BiMAB.

None of them learns from returns (update() only counts), so their whole behaviour is the
sampling law returned by probabilities(): that is what the tests check statistically.
"""
from __future__ import annotations

import numpy as np

from .base import Scheduler
from .config import FixedConfig, ManualConfig, RandomConfig


class FixedPPO(Scheduler):
    """Fixed PPO: always N_sv = N_sv^max, task uniform (no curriculum at all)."""

    name = "fixed"
    config_cls = FixedConfig

    def probabilities(self):
        p_c = np.zeros(self.n_clusters)
        p_c[-1] = 1.0
        return p_c, np.full((self.n_clusters, self.n_arms), 1.0 / self.n_arms)


class RandomCPPO(Scheduler):
    """Random CPPO: every Omega_ij equally likely."""

    name = "random"
    config_cls = RandomConfig

    def probabilities(self):
        return (np.full(self.n_clusters, 1.0 / self.n_clusters),
                np.full((self.n_clusters, self.n_arms), 1.0 / self.n_arms))


class ManualCPPO(Scheduler):
    """Manual CPPO: hand-written stages over the episode budget, with a fixed epsilon.

    The budget is split into len(stages) equal parts by episodes *started* (samples drawn),
    so the schedule follows what the learner has been given, also when several episodes
    run at once. In stage s the cluster is stages[s] with probability 1 - epsilon; with
    probability epsilon any Omega_ij is drawn uniformly. The task is uniform either way, so
    p_arm is uniform and p_cluster = (1 - eps) * onehot(stage) + eps / K. Past the budget the
    last stage stays.
    """

    name = "manual"
    config_cls = ManualConfig

    def __init__(self, config=None, seed: int = 0, total_episodes: int | None = None):
        if total_episodes is None:
            raise ValueError("the 'manual' scheduler needs total_episodes (its stages split the episode budget)")
        super().__init__(config, seed, total_episodes)

    def stage(self) -> int:
        n = len(self.config.stages)
        return min(n - 1, self.n_samples * n // self.total_episodes)

    def probabilities(self):
        eps = self.config.epsilon
        p_c = np.full(self.n_clusters, eps / self.n_clusters)
        p_c[self.config.stages[self.stage()]] += 1.0 - eps
        return p_c, np.full((self.n_clusters, self.n_arms), 1.0 / self.n_arms)

    def _extra_log(self):
        return {"stage": float(self.stage())}

    def load_state_dict(self, d):
        if isinstance(d, dict) and d.get("total_episodes") is None:
            raise ValueError("state: key 'total_episodes' must be set for the 'manual' scheduler")
        super().load_state_dict(d)
