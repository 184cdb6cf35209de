"""Rollout storage, GAE with truncation bootstrap, and the vector-env plumbing.

Torch-free on purpose: the GAE arithmetic is checked against hand-worked numbers in tests
and must not depend on the network code.
"""
from __future__ import annotations

from typing import Any, Callable, Mapping

import numpy as np


def compute_gae(rewards: np.ndarray, values: np.ndarray, next_values: np.ndarray,
                terminated: np.ndarray, episode_end: np.ndarray, gamma: float, lam: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Generalised advantage estimation over a (T, N) rollout.

    ``next_values[t]`` is V(s_{t+1}) of the *same* episode: on a time-limit truncation it is
    the value of the episode's final observation (the state was not terminal, so the
    return continues beyond the cut); after the rollout's last step it is the value of the
    current observation.  On termination the bootstrap is zeroed.  ``episode_end``
    (terminated or truncated) stops the recursion so no advantage leaks across episodes.

        delta_t = r_t + gamma * (1 - term_t) * next_values_t - V(s_t)
        A_t     = delta_t + gamma * lam * (1 - end_t) * A_{t+1}

    Returns (advantages, returns = advantages + values), both float32 (T, N).
    """
    r = np.asarray(rewards, np.float64)
    v = np.asarray(values, np.float64)
    nv = np.asarray(next_values, np.float64)
    term = np.asarray(terminated, bool)
    end = np.asarray(episode_end, bool)
    if not (r.shape == v.shape == nv.shape == term.shape == end.shape):
        raise ValueError(f"GAE inputs must share one shape, got rewards {r.shape}, values {v.shape}, "
                         f"next_values {nv.shape}, terminated {term.shape}, episode_end {end.shape}")
    if np.any(term & ~end):
        raise ValueError("terminated steps must also be marked as episode ends")
    if r.ndim == 1:
        r, v, nv, term, end = (x[:, None] for x in (r, v, nv, term, end))
        squeeze = True
    else:
        squeeze = False
    T = r.shape[0]
    adv = np.zeros_like(r)
    last = np.zeros(r.shape[1:], np.float64)
    for t in range(T - 1, -1, -1):
        delta = r[t] + gamma * (~term[t]) * nv[t] - v[t]
        last = delta + gamma * lam * (~end[t]) * last
        adv[t] = last
    ret = adv + v
    if squeeze:
        adv, ret = adv[:, 0], ret[:, 0]
    return adv.astype(np.float32), ret.astype(np.float32)


class RolloutBuffer:
    """Fixed-capacity (T, N) storage of one rollout; ``size`` steps may be used (early stop)."""

    def __init__(self, steps: int, num_envs: int, obs_dim: int, n_heads: int):
        self.T, self.N = int(steps), int(num_envs)
        self.obs = np.zeros((self.T, self.N, obs_dim), np.float32)
        self.actions = np.zeros((self.T, self.N, n_heads), np.int64)
        self.logp = np.zeros((self.T, self.N), np.float32)
        self.values = np.zeros((self.T, self.N), np.float32)
        self.rewards = np.zeros((self.T, self.N), np.float32)
        self.terminated = np.zeros((self.T, self.N), bool)
        self.ended = np.zeros((self.T, self.N), bool)
        self.next_values = np.zeros((self.T, self.N), np.float32)
        # Truncated steps wait here for one batched critic call: (t, env, normalised final obs).
        self.final_obs: list[tuple[int, int, np.ndarray]] = []
        self.size = 0

    def reset(self) -> None:
        self.final_obs.clear()
        self.size = 0

    def add(self, obs_n, actions, logp, values, rewards, terminated, truncated) -> int:
        t = self.size
        if t >= self.T:
            raise RuntimeError("rollout buffer is full")
        self.obs[t] = obs_n
        self.actions[t] = actions
        self.logp[t] = logp
        self.values[t] = values
        self.rewards[t] = rewards
        self.terminated[t] = terminated
        self.ended[t] = np.asarray(terminated, bool) | np.asarray(truncated, bool)
        self.size = t + 1
        return t

    def finish(self, value_fn: Callable[[np.ndarray], np.ndarray], last_obs_n: np.ndarray,
               gamma: float, lam: float) -> dict[str, np.ndarray]:
        """Fill next_values (in-episode successor, final obs on truncation, last obs at the cut),
        run GAE and return the flattened training arrays."""
        T = self.size
        if T == 0:
            raise ValueError("empty rollout")
        nv = self.next_values[:T]
        nv[:] = 0.0
        if T > 1:
            nv[:-1] = self.values[1:T]
        nv[T - 1] = value_fn(last_obs_n)
        if self.final_obs:
            fv = value_fn(np.stack([o for _, _, o in self.final_obs]))
            for (t, i, _), val in zip(self.final_obs, fv):
                nv[t, i] = val
        # Ended steps whose successor row belongs to a new episode: only truncations (handled
        # above) keep a bootstrap; terminations are zeroed inside compute_gae.
        adv, ret = compute_gae(self.rewards[:T], self.values[:T], nv, self.terminated[:T],
                               self.ended[:T], gamma, lam)
        flat = lambda x: x.reshape((T * self.N,) + x.shape[2:])  # noqa: E731
        return {"obs": flat(self.obs[:T]), "actions": flat(self.actions[:T]),
                "logp": flat(self.logp[:T]), "advantages": flat(adv), "returns": flat(ret),
                "values": flat(self.values[:T])}


# ------------------------------------------------------------------ vector envs
def make_vector_env(env_fn: Callable[[], Any], num_envs: int, mode: str = "batched", workers: int = 1):
    """Vector env with autoreset DISABLED: the trainer resets each finished sub-env itself, with
    that env's own scheduler sample, so the curriculum decides every episode's scenario.

    batched: ``env_fn.make_batch(num_envs)`` (``vec_env.EnvFactory``): all envs in this process,
    one NMPC call and one policy forward per step, in ``workers`` processes of num_envs/workers
    envs each (1 = in this process); async: one subprocess per env; sync: a plain
    loop over ``env_fn()`` envs (any Gymnasium env, e.g. test doubles)."""
    import gymnasium as gym
    from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv

    if mode not in ("batched", "async", "sync"):
        raise ValueError(f"vector mode must be 'batched', 'async' or 'sync', got {mode!r}")
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    fns = [env_fn for _ in range(num_envs)]
    if mode == "batched":
        make_batch = getattr(env_fn, "make_batch", None)
        if not callable(make_batch):
            raise ValueError(f"vector mode 'batched' needs an env factory with make_batch(n) "
                             f"(bimacppo_learning.vec_env.EnvFactory), got {env_fn!r}; use 'sync' or 'async'")
        venv = make_batch(num_envs, workers)
    elif mode == "sync" or num_envs == 1:
        venv = SyncVectorEnv(fns, autoreset_mode=AutoresetMode.DISABLED)
    else:
        venv = AsyncVectorEnv(fns, autoreset_mode=AutoresetMode.DISABLED)
    obs_space, act_space = venv.single_observation_space, venv.single_action_space
    if not isinstance(obs_space, gym.spaces.Box) or len(obs_space.shape) != 1:
        venv.close()
        raise ValueError(f"env observation space must be a 1-D Box, got {obs_space}")
    if not isinstance(act_space, gym.spaces.MultiDiscrete) or act_space.nvec.ndim != 1:
        venv.close()
        raise ValueError(f"env action space must be a 1-D MultiDiscrete, got {act_space}")
    return venv


def close_vector_env(venv, failed: bool) -> None:
    """Close a vector env; after an error, terminate its workers instead of waiting for them.

    An exception between a step's send and its collection (a worker's error, a bad info) leaves
    Gymnasium's AsyncVectorEnv waiting for a step that will never be answered, and its plain
    close() would wait for it forever, hiding the error that got there."""
    from gymnasium.vector import AsyncVectorEnv

    if failed and isinstance(venv, AsyncVectorEnv):
        venv.close(terminate=True)
    else:
        venv.close()


def reset_one(venv, index: int, seed: int | None, options: Mapping[str, Any]) -> tuple[np.ndarray, dict]:
    """Reset sub-env ``index`` alone with its own options (gymnasium 1.4: options['reset_mask']).

    The mask applies the same options to every masked env, hence one env per call.
    Returns that env's observation and info.
    """
    mask = np.zeros(venv.num_envs, dtype=np.bool_)
    mask[index] = True
    seeds: list[int | None] = [None] * venv.num_envs
    seeds[index] = seed
    obs, infos = venv.reset(seed=seeds, options={**options, "reset_mask": mask})
    return np.array(obs[index], np.float32), info_at(infos, index)


def reset_each(venv, seeds: list[int | None], options: list[Mapping[str, Any]]) -> np.ndarray:
    """First reset of a vector env, each sub-env with its own seed and options.

    SyncVectorEnv cannot take a masked reset before one full reset (it has no observations
    to keep for the unmasked envs), so: one full reset with env 0's options, then a masked
    reset of each further env with its own.
    """
    if len(seeds) != venv.num_envs or len(options) != venv.num_envs:
        raise ValueError(f"need {venv.num_envs} seeds and options, got {len(seeds)} and {len(options)}")
    obs, _ = venv.reset(seed=list(seeds), options=dict(options[0]))
    out = np.array(obs, np.float32)
    for i in range(1, venv.num_envs):
        out[i], _ = reset_one(venv, i, seeds[i], options[i])
    return out


def info_at(infos: Mapping[str, Any], index: int) -> dict:
    """Sub-env ``index``'s entries of a gymnasium vector info dict (``_key`` arrays are masks)."""
    out: dict[str, Any] = {}
    for k, v in infos.items():
        if k.startswith("_"):
            continue
        mask = infos.get("_" + k)
        if mask is not None and not bool(mask[index]):
            continue
        if isinstance(v, Mapping):
            out[k] = info_at(v, index)
        else:
            item = v[index]
            out[k] = item.item() if isinstance(item, np.generic) else item
    return out


def vector_spaces(venv) -> tuple[int, tuple[int, ...]]:
    return int(venv.single_observation_space.shape[0]), tuple(int(n) for n in venv.single_action_space.nvec)
