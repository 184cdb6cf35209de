"""The training vector env: B episodes in one process, stepped as one batch.

``BatchedVectorEnv`` is a Gymnasium ``VectorEnv`` over ``batch.IntersectionBatch`` with autoreset
disabled, so the trainer drives it exactly like the subprocess ``AsyncVectorEnv`` (it resets each
finished slot itself, with the curriculum's next scenario, through ``options["reset_mask"]``).
Compared with one subprocess per env it pays no pickling or inter-process hand-off per env and
step, runs one NMPC call and one policy forward for all B. With ``workers`` = W > 1 the B slots
are split into W contiguous blocks, each an ``IntersectionBatch`` in its own process (one message
per block and step), so the worlds, which step one after another inside a block, use every core;
with W = 1 everything runs in the trainer's process and numba spreads the NMPC over the cores.

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

from bimacppo_mpc import MPCConfig
from bimacppo_planner.decision import EnvConfig

from .batch import IntersectionBatch


class BatchedVectorEnv(VectorEnv):
    """See the module docstring. Infos carry the episode summary (``outcome``, ``episode_return``,
    ...) of the slots whose episode ended on that step, with Gymnasium's ``_key`` masks."""

    metadata = {"autoreset_mode": AutoresetMode.DISABLED}

    def __init__(self, num_envs: int, workers: int = 1, **batch_kwargs: Any):
        if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or not 1 <= workers <= num_envs:
            raise ValueError(f"workers must be an integer in 1..num_envs={num_envs}, got {workers!r}")
        self.num_envs = int(num_envs)
        self.workers = int(workers)
        if self.workers == 1:
            self.batch = IntersectionBatch(num_envs, **batch_kwargs)
            self._pool = None
            d, nvec = self.batch.obs_dim, self.batch.nvec
        else:
            self.batch = None
            self._pool = _BlockPool(self.num_envs, self.workers, batch_kwargs)
            d, nvec = self._pool.obs_dim, self._pool.nvec
        self.single_observation_space = spaces.Box(low=-np.inf, high=np.inf, shape=(d,), dtype=np.float32)
        self.single_action_space = spaces.MultiDiscrete(np.array(nvec, dtype=np.int64))
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
            if self._pool is None:
                self._obs[i], info = self.batch.reset(int(i), seeds[i], options)
            else:
                self._obs[i], info = self._pool.reset(int(i), seeds[i], options)
            infos = self._add_info(infos, info, int(i))
        return self._obs.copy(), infos

    def step(self, actions):
        if self._pool is None:
            obs, rew, term, trunc, per_slot = self.batch.step(actions)
        else:
            obs, rew, term, trunc, per_slot = self._pool.step(np.asarray(actions))
        self._obs[:] = obs
        infos: dict = {}
        for i in np.nonzero(term | trunc)[0]:
            summary = {k: v for k, v in per_slot[i].items() if k not in ("x_imr", "lane_change", "commands")}
            infos = self._add_info(infos, summary, int(i))
        return obs, rew, term, trunc, infos

    def mpc_stats(self) -> dict:
        """The NMPC's work so far (``IntersectionBatch.mpc_stats``: seconds in solve_batch,
        problems, SQP iterations, second starts), summed over the blocks (so over processes)."""
        return dict(self.batch.mpc_stats) if self._pool is None else self._pool.mpc_stats()

    def close_extras(self, **kwargs):
        if self._pool is not None:
            self._pool.close()
            self._pool = None


def _block_worker(conn, n: int, batch_kwargs: dict) -> None:
    """One block of slots in its own process: answers (op, args) messages until 'close'.
    Exceptions travel back as ('error', text) so the trainer fails with the worker's message."""
    # The block's NMPC runs on the controller's threads (fast.threads: every core by default),
    # which sleep when idle, so one block's solve can use the core another block leaves idle.
    # Setting numba's count here would change nothing: the controller sets it on every call.
    try:
        batch = IntersectionBatch(n, **batch_kwargs)
        conn.send(("ok", (batch.obs_dim, batch.nvec)))
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises it
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    while True:
        op, arg = conn.recv()
        if op == "close":
            break
        try:
            if op == "mpc_stats":
                out = batch.mpc_stats
            else:
                out = batch.reset(*arg) if op == "reset" else batch.step(arg)
            conn.send(("ok", out))
        except Exception as exc:  # noqa: BLE001
            conn.send(("error", f"{type(exc).__name__}: {exc}"))


class _BlockPool:
    """W processes holding contiguous blocks of slots; used by BatchedVectorEnv(workers=W)."""

    def __init__(self, num_envs: int, workers: int, batch_kwargs: dict):
        import multiprocessing as mp

        ctx = mp.get_context("spawn")   # numba's thread pool and torch are not fork-safe
        sizes = [num_envs // workers + (k < num_envs % workers) for k in range(workers)]
        self.starts = np.cumsum([0] + sizes)
        self.conns, self.procs = [], []
        for n in sizes:
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=_block_worker, args=(child, n, batch_kwargs), daemon=True)
            proc.start()
            child.close()
            self.conns.append(parent)
            self.procs.append(proc)
        metas = [self._answer(c) for c in self.conns]
        self.obs_dim, self.nvec = metas[0]

    def _answer(self, conn):
        try:
            status, out = conn.recv()
        except EOFError:
            self.close()
            raise RuntimeError("a batched env worker process died") from None
        if status == "error":
            self.close()
            raise RuntimeError(f"batched env worker: {out}")
        return out

    def reset(self, i: int, seed, options):
        k = int(np.searchsorted(self.starts, i, side="right") - 1)
        self.conns[k].send(("reset", (i - int(self.starts[k]), seed, options)))
        return self._answer(self.conns[k])

    def step(self, actions: np.ndarray):
        for k, c in enumerate(self.conns):
            c.send(("step", actions[self.starts[k]:self.starts[k + 1]]))
        parts = [self._answer(c) for c in self.conns]
        infos = [info for p in parts for info in p[4]]
        return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                np.concatenate([p[2] for p in parts]), np.concatenate([p[3] for p in parts]), infos)

    def mpc_stats(self) -> dict:
        for c in self.conns:
            c.send(("mpc_stats", None))
        parts = [self._answer(c) for c in self.conns]
        return {k: sum(p[k] for p in parts) for k in parts[0]}

    def close(self) -> None:
        for c in self.conns:
            try:
                c.send(("close", None))
            except (OSError, BrokenPipeError):
                pass
        for p in self.procs:
            p.join(timeout=5)
            if p.is_alive():
                p.kill()
        self.conns, self.procs = [], []


@dataclass(frozen=True)
class EnvFactory:
    """Picklable recipe of the training env; ``factory()`` = one env, ``make_batch(n)`` = n batched."""

    map_id: str = "dual_lane_4way"
    env_config: EnvConfig | None = None
    mpc_solver: str = "fast"
    slow_svs: int = 0
    workers: int = 1
    mpc_config: MPCConfig | None = None      # None: the packaged mpc.yaml
    world_config: Any = None                 # a WorldConfig; None: the packaged world.yaml

    def __call__(self):
        from .env import IntersectionEnv

        return IntersectionEnv(map_id=self.map_id, config=self.env_config, mpc_solver=self.mpc_solver,
                               slow_svs=self.slow_svs, mpc_config=self.mpc_config, world_config=self.world_config)

    def make_batch(self, num_envs: int, workers: int | None = None) -> BatchedVectorEnv:
        return BatchedVectorEnv(num_envs, workers=self.workers if workers is None else workers,
                                map_id=self.map_id, config=self.env_config, mpc_solver=self.mpc_solver,
                                slow_svs=self.slow_svs, mpc_config=self.mpc_config,
                                world_config=self.world_config)
