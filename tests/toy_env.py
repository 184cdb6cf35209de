"""A tiny stand-in for the intersection env, with the same contract, for testing PPO and the loop.

Each step the observation tells the agent which waypoint (of 5), speed (of 5) and lane
action (of 3) is right; surrounding vehicles (n_sv of them) may *block* the way, in which
case the right speed is 0 (yield) and any other speed is a collision.  Three fully right
moves while unblocked reach the goal (success); the time limit ends the episode as a
truncation (timeout).  More SVs = more blocking = harder, so a curriculum over n_sv makes
sense here too.  Layout of the observation mirrors eq. (18): 4 ego entries, then 4 per SV
slot (zero-padded up to max_sv).

Also holds ``ToyScheduler``: a uniform scheduler with the bimacppo_curriculum interface, so
the loop can be tested without the curriculum package.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

NVEC = (5, 5, 3)
N_TASKS = 3
EGO_DIM = NVEC[0] + NVEC[1] + N_TASKS + 2   # one-hot targets, progress, time
SV_DIM = 4


@dataclass(frozen=True)
class ToyEnvConfig:
    max_sv: int = 3
    goal_progress: int = 2          # right moves to reach the goal
    time_limit: int = 4             # steps before a timeout
    block_prob: float = 0.2         # per SV per step
    # The time limit is part of the task by default (time observed, timeout = terminal failure,
    # as the paper's r_F makes it).  Shaping is a penalty per wrong sub-action, so "never
    # finish" earns nothing, and collision_reward is below the worst possible continuation
    # (3 * wrong_head_reward * time_limit), so crashing early never pays either.
    # timeout_terminates=False makes the limit a truncation (bootstrapped from the final
    # observation) to exercise that path of the loop.
    timeout_terminates: bool = True
    wrong_head_reward: float = -0.1       # per wrong sub-action (dense shaping, keeps the toy quick)
    success_reward: float = 1.0
    success_reward_per_sv: float = 0.25   # like alpha_1 * N_sv in eq. (26)
    collision_reward: float = -1.5

    def __post_init__(self) -> None:
        if self.max_sv < 0 or self.goal_progress < 1 or self.time_limit < 1:
            raise ValueError(f"invalid ToyEnvConfig {self}")
        if not 0.0 <= self.block_prob < 1.0:
            raise ValueError(f"block_prob must be in [0, 1), got {self.block_prob}")


class ToyIntersectionEnv(gym.Env):
    """MultiDiscrete([5, 5, 3]) toy task; reset(options={"n_sv": i, "task": j})."""

    metadata = {"render_modes": []}

    def __init__(self, config: ToyEnvConfig | None = None):
        self.cfg = config or ToyEnvConfig()
        dim = EGO_DIM + SV_DIM * self.cfg.max_sv
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (dim,), np.float32)
        self.action_space = gym.spaces.MultiDiscrete(np.array(NVEC, np.int64))
        self.n_sv = 0
        self.task = 0
        self._t = 0
        self._progress = 0
        self._ret = 0.0
        self._done = True
        self._targets = np.zeros(2, np.int64)
        self._blocking = np.zeros(0, bool)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        opts = dict(options or {})
        n_sv = opts.pop("n_sv", None)
        task = opts.pop("task", None)
        if opts:
            raise ValueError(f"unknown reset option(s): {sorted(opts)}")
        if n_sv is None:
            n_sv = int(self.np_random.integers(self.cfg.max_sv + 1))
        if task is None:
            task = int(self.np_random.integers(N_TASKS))
        if isinstance(n_sv, bool) or not isinstance(n_sv, (int, np.integer)) or not 0 <= n_sv <= self.cfg.max_sv:
            raise ValueError(f"n_sv must be an int in [0, {self.cfg.max_sv}], got {n_sv!r}")
        if isinstance(task, bool) or not isinstance(task, (int, np.integer)) or not 0 <= task < N_TASKS:
            raise ValueError(f"task must be an int in [0, {N_TASKS - 1}], got {task!r}")
        self.n_sv, self.task = int(n_sv), int(task)
        self._t, self._progress, self._ret, self._done = 0, 0, 0.0, False
        self._draw()
        return self._obs(), {"n_sv": self.n_sv, "task": self.task}

    def _draw(self) -> None:
        self._targets = self.np_random.integers(0, [NVEC[0], NVEC[1]])
        self._blocking = self.np_random.random(self.n_sv) < self.cfg.block_prob

    def _obs(self) -> np.ndarray:
        o = np.zeros(self.observation_space.shape, np.float32)
        # One-hot targets keep the right answer a linear function of the observation: the toy
        # exercises the PPO machinery, not the network's capacity.
        o[self._targets[0]] = 1.0
        o[NVEC[0] + self._targets[1]] = 1.0
        o[NVEC[0] + NVEC[1] + self.task] = 1.0
        o[EGO_DIM - 2] = self._progress / self.cfg.goal_progress
        o[EGO_DIM - 1] = self._t / self.cfg.time_limit
        for k in range(self.n_sv):
            base = EGO_DIM + SV_DIM * k
            o[base] = float(self._blocking[k])
            o[base + 1: base + 3] = self.np_random.uniform(-1.0, 1.0, 2)   # distractors
            o[base + 3] = 1.0                                               # slot present
        return o

    def step(self, action):
        if self._done:
            raise RuntimeError("step() called on a finished episode; call reset() first")
        a = np.asarray(action).reshape(-1)
        if a.shape != (3,) or not self.action_space.contains(a.astype(np.int64)):
            raise ValueError(f"action must be 3 ints within {list(NVEC)}, got {action!r}")
        c = self.cfg
        self._t += 1
        blocked = bool(self._blocking.any())
        right_speed = 0 if blocked else int(self._targets[1])
        right = (int(a[0]) == self._targets[0], int(a[1]) == right_speed, int(a[2]) == self.task)
        reward = 0.0
        terminated = truncated = False
        outcome = None
        if blocked and a[1] > 0:
            reward += c.collision_reward
            terminated, outcome = True, "collision"
        else:
            reward += c.wrong_head_reward * (3 - sum(right))
            if all(right):      # yielding correctly (speed 0 while blocked) is a right move too
                self._progress += 1
            if self._progress >= c.goal_progress:
                reward += c.success_reward + c.success_reward_per_sv * self.n_sv
                terminated, outcome = True, "success"
            elif self._t >= c.time_limit:
                outcome = "timeout"
                if c.timeout_terminates:
                    terminated = True
                else:
                    truncated = True
        self._ret += reward
        info: dict[str, Any] = {}
        if terminated or truncated:
            self._done = True
            info = {"outcome": outcome, "n_sv": self.n_sv, "task": self.task,
                    "episode_return": self._ret}
        else:
            self._draw()
        return self._obs(), float(reward), terminated, truncated, info

    def expert_action(self) -> np.ndarray:
        """The right action for the current observation (an upper bound for tests)."""
        speed = 0 if self._blocking.any() else int(self._targets[1])
        return np.array([self._targets[0], speed, self.task], np.int64)


class ToyScheduler:
    """Uniform over (n_sv, task) with the bimacppo_curriculum scheduler interface."""

    def __init__(self, n_clusters: int = 4, n_arms: int = N_TASKS, seed: int = 0):
        self.n_clusters, self.n_arms = int(n_clusters), int(n_arms)
        self.rng = np.random.default_rng(seed)
        self.counts = np.zeros((self.n_clusters, self.n_arms), np.int64)
        self.sum_return = np.zeros((self.n_clusters, self.n_arms), np.float64)

    def sample(self) -> tuple[int, int]:
        return int(self.rng.integers(self.n_clusters)), int(self.rng.integers(self.n_arms))

    def update(self, i: int, j: int, episode_return: float) -> None:
        if not np.isfinite(episode_return):
            raise ValueError(f"episode_return must be finite, got {episode_return}")
        self.counts[i, j] += 1
        self.sum_return[i, j] += episode_return

    def probabilities(self) -> tuple[np.ndarray, np.ndarray]:
        return (np.full(self.n_clusters, 1.0 / self.n_clusters),
                np.full((self.n_clusters, self.n_arms), 1.0 / self.n_arms))

    def log_dict(self) -> dict[str, float]:
        out = {f"p_cluster_{i}": 1.0 / self.n_clusters for i in range(self.n_clusters)}
        out.update({f"count_{i}_{j}": float(self.counts[i, j])
                    for i in range(self.n_clusters) for j in range(self.n_arms)})
        return out

    def state_dict(self) -> dict:
        return {"rng": self.rng.bit_generator.state, "counts": self.counts.tolist(),
                "sum_return": self.sum_return.tolist()}

    def load_state_dict(self, d: dict) -> None:
        self.rng.bit_generator.state = d["rng"]
        self.counts = np.asarray(d["counts"], np.int64)
        self.sum_return = np.asarray(d["sum_return"], np.float64)


def evaluate_toy(agent, n_per_sv: int = 100, seed: int = 10_000) -> dict[int, dict[str, int]]:
    """Deterministic-policy outcomes per n_sv on fixed seeds (tasks cycled)."""
    env = ToyIntersectionEnv()
    out: dict[int, dict[str, int]] = {}
    for n_sv in range(env.cfg.max_sv + 1):
        counts = {"success": 0, "collision": 0, "timeout": 0}
        for k in range(n_per_sv):
            obs, _ = env.reset(seed=seed + 1000 * n_sv + k, options={"n_sv": n_sv, "task": k % N_TASKS})
            done = False
            while not done:
                a, _, _ = agent.act(agent.normalize_obs(obs[None]), deterministic=True)
                obs, _, term, trunc, info = env.step(a[0])
                done = term or trunc
            counts[info["outcome"]] += 1
        out[n_sv] = counts
    return out


def _main() -> None:
    """Train PPO on the toy env: a smoke test of the whole loop (python tests/toy_env.py)."""
    import argparse
    import json
    import time

    from bimacppo_learning.ppo_config import load_config
    from bimacppo_learning.trainer import Trainer

    ap = argparse.ArgumentParser(description=_main.__doc__)
    ap.add_argument("--episodes", type=int, default=3500)
    ap.add_argument("--run-dir", required=True)
    ap.add_argument("--vector", choices=("sync", "async"), default="sync")
    ap.add_argument("--num-envs", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rollout-steps", type=int, default=128)
    ap.add_argument("--minibatch-size", type=int, default=64)
    ap.add_argument("--resume", action="store_true")
    args = ap.parse_args()
    pcfg, tcfg = load_config(ppo={"minibatch_size": args.minibatch_size},
                             train={"vector": args.vector, "num_envs": args.num_envs, "batch_workers": 1, "seed": args.seed,
                                    "rollout_steps": args.rollout_steps})
    tr = Trainer(ToyIntersectionEnv, ToyScheduler(seed=args.seed), args.run_dir, pcfg, tcfg)
    t0 = time.monotonic()
    res = tr.train(args.episodes, resume=args.resume)
    wall = time.monotonic() - t0
    print(json.dumps({"episodes": res.episodes, "env_steps": res.env_steps, "updates": res.updates,
                      "wall_s": round(wall, 1), "steps_per_s": round(res.env_steps / wall, 1),
                      "train_success_last_window": res.success_rate,
                      "eval_deterministic": evaluate_toy(tr.agent)}))


if __name__ == "__main__":
    _main()
