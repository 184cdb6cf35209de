"""The interface every curriculum scheduler shares (see docs/architecture.md).

A scheduler owns a two-level sampling law over the scenarios Omega_ij (cluster i = N_sv,
arm j = EV task). Sampling is always "cluster from p_cluster, then arm from p_arm[i]", with
one uniform draw per level, so the number of random draws per episode is the same for
every scheduler and a seed fixes the whole sequence. Subclasses only say what the two
distributions are and how a finished episode's return changes them.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

N_TASKS = 3  # left, straight, right: the paper's arms j = 0, 1, 2 (bimacppo_common.conventions.TASKS)
STATE_VERSION = 1


def draw(p: np.ndarray, u: float) -> int:
    """Inverse-CDF draw; the clip guards against u landing past a cumsum that rounds below 1."""
    return int(min(np.searchsorted(np.cumsum(p), u, side="right"), len(p) - 1))


def _json_rng_state(state: dict) -> dict:
    """numpy's bit-generator state holds only dicts, strings and Python ints: JSON-safe as is."""
    return {k: (_json_rng_state(v) if isinstance(v, dict) else (int(v) if isinstance(v, (np.integer,)) else v))
            for k, v in state.items()}


class Scheduler:
    """Base class: sampling, bookkeeping, validation and (de)serialisation."""

    name = "base"
    config_cls: Any = None

    def __init__(self, config=None, seed: int = 0, total_episodes: int | None = None):
        self.config = self.config_cls.resolve(config)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        if total_episodes is not None and (isinstance(total_episodes, bool)
                                           or not isinstance(total_episodes, (int, np.integer))
                                           or total_episodes < 1):
            raise ValueError(f"total_episodes must be a positive integer or None, got {total_episodes!r}")
        self.seed = int(seed)
        self.total_episodes = None if total_episodes is None else int(total_episodes)
        self.n_clusters = self.config.n_sv_max + 1
        self.n_arms = N_TASKS
        self.rng = np.random.Generator(np.random.PCG64(self.seed))
        self.counts = np.zeros((self.n_clusters, self.n_arms), dtype=np.int64)  # sampled times (Table I)
        self.n_samples = 0
        self.n_updates = 0

    # ----------------------------------------------------------------- public API
    def probabilities(self) -> tuple[np.ndarray, np.ndarray]:
        """(p_cluster (K,), p_arm (K, 3)): the law the next sample() draws from."""
        raise NotImplementedError

    def sample(self) -> tuple[int, int]:
        p_c, p_a = self.probabilities()
        i = draw(p_c, self.rng.random())
        j = draw(p_a[i], self.rng.random())
        self.counts[i, j] += 1
        self.n_samples += 1
        self._on_sample(i, j, float(p_c[i]), float(p_a[i, j]))
        return i, j

    def update(self, i: int, j: int, episode_return: float) -> None:
        i, j = self._check_index(i, j)
        if isinstance(episode_return, bool) or not isinstance(episode_return, (int, float, np.integer, np.floating)):
            raise ValueError(f"episode_return must be a real number, got {type(episode_return).__name__}")
        r = float(episode_return)
        if not math.isfinite(r):
            raise ValueError(f"episode_return must be finite, got {r!r}")
        self.n_updates += 1
        self._update(i, j, r)

    def log_dict(self) -> dict[str, float]:
        p_c, p_a = self.probabilities()
        out = {"episodes": float(self.n_updates), "samples": float(self.n_samples)}
        for i in range(self.n_clusters):
            out[f"cluster_prob_{i}"] = float(p_c[i])
            out[f"count_{i}"] = float(self.counts[i].sum())
            for j in range(self.n_arms):
                out[f"arm_prob_{i}_{j}"] = float(p_a[i, j])
                out[f"count_{i}_{j}"] = float(self.counts[i, j])
        out.update(self._extra_log())
        return out

    def state_dict(self) -> dict:
        return {
            "scheduler": self.name,
            "version": STATE_VERSION,
            "config": self.config.to_dict(),
            "seed": self.seed,
            "total_episodes": self.total_episodes,
            "rng": _json_rng_state(self.rng.bit_generator.state),
            "n_samples": self.n_samples,
            "n_updates": self.n_updates,
            "counts": self.counts.tolist(),
            **self._extra_state(),
        }

    def load_state_dict(self, d: dict) -> None:
        if not isinstance(d, dict):
            raise ValueError(f"state must be a dict, got {type(d).__name__}")
        for key in ("scheduler", "version", "config", "seed", "total_episodes", "rng", "n_samples", "n_updates", "counts"):
            if key not in d:
                raise ValueError(f"state: missing key '{key}'")
        if d["scheduler"] != self.name:
            raise ValueError(f"state: key 'scheduler' is {d['scheduler']!r}, this scheduler is {self.name!r}")
        if d["version"] != STATE_VERSION:
            raise ValueError(f"state: key 'version' is {d['version']!r}, expected {STATE_VERSION}")
        # The saved config is read the way a config file is (a key saved before it existed takes
        # the packaged default), so only a value that really differs refuses the state.
        saved = self.config_cls.from_dict(d["config"], source="state: key 'config'").to_dict()
        mine = self.config.to_dict()
        if saved != mine:
            diff = sorted(k for k in mine if mine[k] != saved[k])
            raise ValueError(f"state: key 'config' differs from this scheduler's config in {diff}; "
                             f"build the scheduler with the saved config to resume")
        counts = np.asarray(d["counts"], dtype=np.int64)
        if counts.shape != self.counts.shape:
            raise ValueError(f"state: key 'counts' has shape {counts.shape}, expected {self.counts.shape}")
        rng = np.random.Generator(np.random.PCG64())
        try:
            rng.bit_generator.state = d["rng"]
        except (TypeError, ValueError, KeyError) as exc:
            raise ValueError(f"state: key 'rng' is not a PCG64 state ({exc})") from exc
        self._load_extra_state(d)  # validates before anything below is touched
        self.seed = int(d["seed"])
        self.total_episodes = d["total_episodes"]
        self.rng = rng
        self.n_samples = int(d["n_samples"])
        self.n_updates = int(d["n_updates"])
        self.counts = counts

    # ----------------------------------------------------------------- hooks
    def _on_sample(self, i: int, j: int, p_i: float, p_ij: float) -> None:
        """Called after each draw with the probabilities the draw used."""

    def _update(self, i: int, j: int, r: float) -> None:
        """Baselines ignore returns; bandits learn from them."""

    def _extra_log(self) -> dict[str, float]:
        return {}

    def _extra_state(self) -> dict:
        return {}

    def _load_extra_state(self, d: dict) -> None:
        pass

    # ----------------------------------------------------------------- helpers
    def _check_index(self, i, j) -> tuple[int, int]:
        for name, v, n in (("cluster i (N_sv)", i, self.n_clusters), ("arm j (task)", j, self.n_arms)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise ValueError(f"{name} must be an integer, got {type(v).__name__} {v!r}")
            if not 0 <= v < n:
                raise ValueError(f"{name} must be in 0..{n - 1}, got {v}")
        return int(i), int(j)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(seed={self.seed}, episodes={self.n_updates}, samples={self.n_samples})"
