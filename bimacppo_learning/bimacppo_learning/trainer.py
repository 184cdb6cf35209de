"""The training loop: curriculum-scheduled episodes on vector envs, PPO updates, logs, checkpoints.

Generic over any env with the planner contract (reset(options={"n_sv", "task"}), MultiDiscrete
action, ``info["outcome"]`` at episode end) and any scheduler with the bimacppo_curriculum
interface.  The scheduler lives here, in the main process: every finished sub-env reports its
return to it and is reset alone with the scheduler's next sample (autoreset is disabled), so
each episode's scenario comes from the curriculum, as in Algorithm 2.

Checkpoints are written at update boundaries once ``checkpoint_every`` more episodes have
finished; episodes still in flight at that moment are not saved (their envs live in worker
processes), so a resume restarts them with fresh scheduler samples.  Loss on a kill is
therefore at most one checkpoint interval plus one rollout.
"""
from __future__ import annotations

import collections
import json
import logging
import os
import pathlib
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np
import torch

from bimacppo_common.conventions import OUTCOMES

from .checkpoint import (CHECKPOINT_FORMAT, FORMAT_VERSION, CheckpointError, checkpoint_path,
                         export_policy, latest_checkpoint, list_checkpoints, load_checkpoint,
                         restore_agent, save_checkpoint)
from .ppo import PPO
from .ppo_config import PPOConfig, TrainConfig, config_from_dict, config_to_dict, load_config
from .rollout import (RolloutBuffer, close_vector_env, info_at, make_vector_env, reset_each, reset_one,
                      vector_spaces)

log = logging.getLogger(__name__)

SEED_HIGH = 2 ** 31 - 1


@dataclass(frozen=True)
class TrainResult:
    episodes: int
    env_steps: int
    updates: int
    success_rate: float          # over the last `success_window` episodes
    run_dir: pathlib.Path
    history_path: pathlib.Path
    last_checkpoint: pathlib.Path | None
    timing: dict                 # seconds of this call in env / policy / update / total, and the CPU seconds of this
                                 # process (every thread; worker processes not included) in each: env_cpu / policy_cpu /
                                 # update_cpu / total_cpu; batched: mpc_seconds (wall seconds in solve_batch),
                                 # mpc_cpu_seconds (CPU seconds in it), mpc_problems, mpc_iterations, mpc_second_starts
                                 # (summed over workers)


class Trainer:
    """PPO + curriculum training over an episode budget.

    Args:
        env_fn: zero-argument factory of one env (picklable for the async vector env).
        scheduler: object with sample/update/log_dict/state_dict/load_state_dict.
        run_dir: where history.jsonl, tb/, checkpoints/ and policy.pt go.
        ppo_config, train_config: default to the packaged config/ppo.yaml (ppo_config: to a given
            agent's own config). A given agent adopts ppo_config (``PPO.adopt_config``).
        agent: a prebuilt PPO (else one is built from the env's spaces).
        on_episode: optional callback(record) after each finished episode (hooks for tests/CLI).
        run_meta: how the run was set up (env and MPC config, curriculum, map, seed, ...; JSON-able):
            saved in every checkpoint under "run" and in the exported policy's metadata, so that
            deployment rebuilds the same observation and decoding, evaluation runs the same NMPC
            and a resume can check both.
    """

    def __init__(self, env_fn: Callable[[], Any], scheduler: Any, run_dir: str | os.PathLike,
                 ppo_config: PPOConfig | None = None, train_config: TrainConfig | None = None,
                 agent: PPO | None = None, on_episode: Callable[[dict], None] | None = None,
                 run_meta: Mapping[str, Any] | None = None):
        for m in ("sample", "update", "log_dict", "state_dict", "load_state_dict"):
            if not callable(getattr(scheduler, m, None)):
                raise TypeError(f"scheduler lacks method {m}()")
        if ppo_config is None or train_config is None:
            p, t = load_config()
            ppo_config = ppo_config or (agent.cfg if agent is not None else p)
            train_config = train_config or t
        if agent is not None and agent.cfg != ppo_config:
            # The run's PPO config is what trains and what its checkpoints record, also for a
            # prebuilt agent (a fine-tune's source was trained under its own).
            agent.adopt_config(ppo_config)
        self.pcfg, self.tcfg = ppo_config, train_config
        self.env_fn = env_fn
        self.scheduler = scheduler
        self.run_dir = pathlib.Path(run_dir)
        self.ckpt_dir = self.run_dir / "checkpoints"
        self.history_path = self.run_dir / "history.jsonl"
        self.on_episode = on_episode
        self.run_meta = dict(run_meta or {})
        self.agent = agent
        self.episodes = 0
        self.env_steps = 0
        self.updates = 0
        self.episode_rng = np.random.default_rng(self.tcfg.seed)
        self.window: collections.deque[int] = collections.deque(maxlen=self.tcfg.success_window)
        self.last_checkpoint: pathlib.Path | None = None
        self._last_ckpt_episodes = 0
        self.timing = {"env": 0.0, "policy": 0.0, "update": 0.0, "total": 0.0,
                       "env_cpu": 0.0, "policy_cpu": 0.0, "update_cpu": 0.0, "total_cpu": 0.0}
        self._wall_offset = 0.0      # wall_s of the last kept episode when resuming

    # ------------------------------------------------------------------ public
    def train(self, episodes: int, resume: bool = False) -> TrainResult:
        """Run until ``episodes`` episodes have finished in total (counting resumed ones)."""
        if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
            raise ValueError(f"episodes must be a positive int, got {episodes!r}")
        torch.set_num_threads(self.tcfg.torch_threads)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        venv = make_vector_env(self.env_fn, self.tcfg.num_envs, self.tcfg.vector, self.tcfg.workers)
        writer = None
        bar = None
        failed = True
        try:
            obs_dim, nvec = vector_spaces(venv)
            if self.agent is None:
                self.agent = PPO(obs_dim, nvec, self.pcfg, seed=self.tcfg.seed)
            elif (self.agent.obs_dim, self.agent.nvec) != (obs_dim, nvec):
                raise ValueError(f"agent has obs_dim={self.agent.obs_dim}, nvec={self.agent.nvec}; "
                                 f"env has obs_dim={obs_dim}, nvec={nvec}")
            self._start(resume)
            if self.episodes >= episodes:
                log.info("budget of %d episodes already reached (%d done)", episodes, self.episodes)
                return self._result()
            if self.tcfg.tensorboard:
                from torch.utils.tensorboard import SummaryWriter
                writer = SummaryWriter(str(self.run_dir / "tb"), purge_step=self.episodes + 1)
            if self.tcfg.progress_bar:
                from tqdm.auto import tqdm
                bar = tqdm(total=episodes, initial=self.episodes, unit="ep", dynamic_ncols=True)
            self._loop(venv, episodes, writer, bar)
            self.save()
            export_policy(self.agent, self.run_dir / "policy.pt",
                          meta={**self.run_meta, "episodes": self.episodes, "env_steps": self.env_steps,
                                "seed": self.tcfg.seed})
            failed = False
            return self._result()
        finally:
            if bar is not None:
                bar.close()
            if writer is not None:
                writer.close()
            close_vector_env(venv, failed)

    def save(self) -> pathlib.Path:
        """Write a checkpoint of everything needed to continue (atomic); prune old ones."""
        path = checkpoint_path(self.ckpt_dir, self.episodes)
        save_checkpoint(path, self._payload())
        self.last_checkpoint = path
        self._last_ckpt_episodes = self.episodes
        for old in list_checkpoints(self.ckpt_dir)[:-self.tcfg.keep_checkpoints]:
            old.unlink(missing_ok=True)
        return path

    # ------------------------------------------------------------ internals
    def _payload(self) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "version": FORMAT_VERSION,
            "agent": self.agent.state_dict(),
            "config": config_to_dict(self.pcfg, self.tcfg),
            "scheduler_state": json.dumps(self.scheduler.state_dict()),
            "counters": {"episodes": self.episodes, "env_steps": self.env_steps,
                         "updates": self.updates},
            "rng": {"episode_rng": self.episode_rng.bit_generator.state,
                    "torch": torch.get_rng_state()},
            "success_window": list(self.window),
            "run": json.dumps(self.run_meta),
        }

    def _start(self, resume: bool) -> None:
        latest = latest_checkpoint(self.ckpt_dir)
        if not resume:
            if latest is not None:
                raise ValueError(f"{self.run_dir} already holds checkpoints ({latest.name}); "
                                 "pass resume=True to continue, or use a new run_dir")
            self.history_path.write_text("")
            return
        if latest is None:
            log.warning("resume requested but %s has no checkpoint: starting fresh", self.ckpt_dir)
            self.history_path.write_text("")
            return
        self._restore(latest)

    def _restore(self, path: pathlib.Path) -> None:
        d = load_checkpoint(path)
        try:
            saved_pcfg, _ = config_from_dict(d["config"], source=str(path))
        except ValueError as exc:
            raise CheckpointError(path, f"config is invalid: {exc}") from None
        if saved_pcfg != self.pcfg:
            diff = sorted(k for k in config_to_dict(self.pcfg)["ppo"]
                          if config_to_dict(self.pcfg)["ppo"][k] != config_to_dict(saved_pcfg)["ppo"][k])
            raise CheckpointError(path, f"was trained with a different PPO config (keys {diff}); "
                                        "resume with the same ppo section")
        restore_agent(self.agent, d["agent"], path)
        try:
            self.scheduler.load_state_dict(json.loads(d["scheduler_state"]))
            c = d["counters"]
            self.episodes, self.env_steps, self.updates = int(c["episodes"]), int(c["env_steps"]), int(c["updates"])
            self.episode_rng.bit_generator.state = d["rng"]["episode_rng"]
            torch.set_rng_state(d["rng"]["torch"])
            self.window.clear()
            self.window.extend(int(x) for x in d.get("success_window", []))
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(path, f"malformed training state: {type(exc).__name__}: {exc}") from None
        self._last_ckpt_episodes = self.episodes
        self.last_checkpoint = path
        self._truncate_history(self.episodes)
        log.info("resumed from %s at episode %d", path, self.episodes)

    def _truncate_history(self, episodes: int) -> None:
        """Drop records of episodes after the checkpoint: they will be replayed. The kept
        records' last ``wall_s`` becomes the clock's offset, so ``wall_s`` counts the training
        time of the whole run across resumes (episodes/s stay comparable)."""
        kept = []
        self._wall_offset = 0.0
        if self.history_path.exists():
            for line in self.history_path.read_text().splitlines():
                if line.strip():
                    rec = json.loads(line)
                    if rec["episode"] <= episodes:
                        kept.append(line)
                        self._wall_offset = float(rec.get("wall_s", self._wall_offset))
        tmp = self.history_path.with_suffix(".jsonl.tmp")
        tmp.write_text("".join(k + "\n" for k in kept))
        os.replace(tmp, self.history_path)

    def _draw_episode(self) -> tuple[dict, int, dict]:
        n_sv, task = self.scheduler.sample()
        seed = int(self.episode_rng.integers(SEED_HIGH))
        slot = {"n_sv": int(n_sv), "task": int(task), "seed": seed, "ret": 0.0, "len": 0}
        return slot, seed, {"n_sv": int(n_sv), "task": int(task)}

    def _new_episode(self, venv, i: int, slots: list[dict]) -> np.ndarray:
        slots[i], seed, opts = self._draw_episode()
        obs, _ = reset_one(venv, i, seed, opts)
        return obs

    def _loop(self, venv, budget: int, writer, bar) -> None:
        agent = self.agent
        N, T = venv.num_envs, self.tcfg.rollout_steps
        buf = RolloutBuffer(T, N, agent.obs_dim, len(agent.nvec))
        draws = [self._draw_episode() for _ in range(N)]
        slots: list[dict] = [d[0] for d in draws]
        obs = reset_each(venv, [d[1] for d in draws], [d[2] for d in draws])
        hist = self.history_path.open("a")
        t0 = time.monotonic() - self._wall_offset
        tm = self.timing
        p0, q0 = time.perf_counter(), time.process_time()
        try:
            while self.episodes < budget:
                buf.reset()
                done_budget = False
                for _ in range(T):
                    c0, d0 = time.perf_counter(), time.process_time()
                    obs_n = agent.normalize_obs(obs, update=True)
                    actions, logp, values = agent.act(obs_n)
                    c1, d1 = time.perf_counter(), time.process_time()
                    nxt, rew, term, trunc, infos = venv.step(actions)
                    # after every env step: a numba parallel call in it (the batched NMPC) sets
                    # the OpenMP thread count torch's operators read, and the next forwards (the
                    # policy's, the value bootstrap's) would run on every core, waking idle
                    # threads for tiny ops
                    torch.set_num_threads(self.tcfg.torch_threads)
                    c2, d2 = time.perf_counter(), time.process_time()
                    tm["policy"] += c1 - c0
                    tm["env"] += c2 - c1
                    tm["policy_cpu"] += d1 - d0
                    tm["env_cpu"] += d2 - d1
                    rew = np.asarray(rew, np.float64)
                    if not np.all(np.isfinite(rew)):
                        raise ValueError(f"env returned a non-finite reward: {rew}")
                    t = buf.add(obs_n, actions, logp, values, rew, term, trunc)
                    self.env_steps += N
                    nxt = np.array(nxt, np.float32)
                    for i in range(N):
                        slots[i]["ret"] += float(rew[i])
                        slots[i]["len"] += 1
                        if not (term[i] or trunc[i]):
                            continue
                        if trunc[i] and not term[i]:
                            buf.final_obs.append((t, i, agent.normalize_obs(nxt[i][None])[0]))
                        if not done_budget:
                            self._finish_episode(info_at(infos, i), slots[i], bool(term[i]),
                                                 hist, writer, bar, time.monotonic() - t0)
                            done_budget = self.episodes >= budget
                        if not done_budget:
                            c3, d3 = time.perf_counter(), time.process_time()
                            nxt[i] = self._new_episode(venv, i, slots)
                            tm["env"] += time.perf_counter() - c3
                            tm["env_cpu"] += time.process_time() - d3
                    obs = nxt
                    if done_budget:
                        break
                if buf.size * N >= 2:
                    c4, d4 = time.perf_counter(), time.process_time()
                    agent.set_progress(self.episodes / budget)
                    self._update(buf, obs, writer)
                    tm["update"] += time.perf_counter() - c4
                    tm["update_cpu"] += time.process_time() - d4
                if (self.episodes - self._last_ckpt_episodes >= self.tcfg.checkpoint_every
                        and self.episodes < budget):
                    self.save()
        finally:
            tm["total"] += time.perf_counter() - p0
            tm["total_cpu"] += time.process_time() - q0
            if callable(getattr(venv, "mpc_stats", None)):
                mst = venv.mpc_stats()               # summed over all worker processes
                tm.update({f"mpc_{k}": v for k, v in mst.items()})
            hist.close()

    def _finish_episode(self, info: Mapping[str, Any], slot: dict, terminated: bool, hist,
                        writer, bar, elapsed: float) -> None:
        outcome = info.get("outcome")
        if outcome not in OUTCOMES:
            raise ValueError(f"env ended an episode without a valid info['outcome'] "
                             f"(got {outcome!r}; expected one of {OUTCOMES})")
        env_ret = info.get("episode_return", slot["ret"])
        env_ret = float(env_ret)
        self.scheduler.update(slot["n_sv"], slot["task"], env_ret)
        self.episodes += 1
        self.window.append(int(outcome == "success"))
        sr = float(np.mean(self.window))
        sched = {k: float(v) for k, v in self.scheduler.log_dict().items()}
        rec = {"episode": self.episodes, "return": slot["ret"], "episode_return": env_ret,
               "length": slot["len"], "ticks": int(info.get("episode_ticks", 0)),
               "outcome": outcome, "terminated": terminated,
               "n_sv": slot["n_sv"], "task": slot["task"], "seed": slot["seed"],
               "env_steps": self.env_steps, "updates": self.updates,
               "success_rate": sr, "wall_s": round(elapsed, 3), "scheduler": sched}
        hist.write(json.dumps(rec) + "\n")
        hist.flush()
        if writer is not None and self.episodes % self.tcfg.tensorboard_every == 0:
            e = self.episodes
            writer.add_scalar("episode/return", slot["ret"], e)
            writer.add_scalar("episode/episode_return", env_ret, e)
            writer.add_scalar("episode/length", slot["len"], e)
            for o in OUTCOMES:
                writer.add_scalar(f"episode/{o}", float(outcome == o), e)
            writer.add_scalar("episode/n_sv", slot["n_sv"], e)
            writer.add_scalar("episode/task", slot["task"], e)
            writer.add_scalar("episode/success_rate", sr, e)
            for k, v in sched.items():
                writer.add_scalar(f"curriculum/{k}", v, e)
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"succ={sr:.2f} {self._probs_str(sched)}", refresh=False)
        if self.on_episode is not None:
            self.on_episode(rec)

    def _probs_str(self, sched: Mapping[str, float]) -> str:
        probs = getattr(self.scheduler, "probabilities", None)
        if callable(probs):
            p_c = np.asarray(probs()[0], float).reshape(-1)
            return "p_nsv=" + "/".join(f"{p:.2f}" for p in p_c)
        keys = [k for k in sched if "prob" in k.lower() or k.startswith("p_")]
        return " ".join(f"{k}={sched[k]:.2f}" for k in keys[:6])

    def _update(self, buf: RolloutBuffer, obs: np.ndarray, writer) -> None:
        agent, cfg = self.agent, self.pcfg
        last_n = agent.normalize_obs(obs)
        data = buf.finish(agent.value, last_n, cfg.gamma, cfg.gae_lambda)
        t0 = time.monotonic()
        torch.set_num_threads(self.tcfg.update_threads or os.cpu_count() or 1)
        try:
            stats = agent.update(data["obs"], data["actions"], data["logp"], data["advantages"],
                                 data["returns"], fit_actor=self.updates >= cfg.critic_warmup_updates,
                                 critic_thread=self.tcfg.critic_thread)
        finally:
            torch.set_num_threads(self.tcfg.torch_threads)
        stats["update_s"] = time.monotonic() - t0
        stats["actor_lr"] = float(agent.actor_opt.param_groups[0]["lr"])
        stats["entropy_coef"] = float(agent.entropy_coef)
        stats["samples"] = float(data["obs"].shape[0])
        self.updates += 1
        if writer is not None:
            for k, v in stats.items():
                writer.add_scalar(f"update/{k}", v, self.episodes)
            writer.add_scalar("update/env_steps", self.env_steps, self.episodes)

    def _result(self) -> TrainResult:
        return TrainResult(self.episodes, self.env_steps, self.updates,
                           float(np.mean(self.window)) if self.window else float("nan"),
                           self.run_dir, self.history_path, self.last_checkpoint, dict(self.timing))


def load_agent(path: str | os.PathLike, seed: int = 0) -> PPO:
    """Rebuild a full PPO agent (e.g. for fine-tuning, paper §IV-C) from a training checkpoint or
    a policy export (``load_fine_tune_source``)."""
    return load_fine_tune_source(path, seed)[0]


def load_fine_tune_source(path: str | os.PathLike, seed: int = 0) -> tuple[PPO, dict, bool]:
    """(agent, run metadata, whether the critic is fresh) for a fine-tune from ``path``.

    A training checkpoint gives its whole agent (actor, critic, optimiser moments, normaliser)
    under the PPO config it was trained with. A policy export carries only what acting needs,
    so the agent gets its actor and normaliser under the packaged PPO config with the export's
    network shape, a critic initialised from ``seed``, and fresh optimisers; the run's
    ``critic_warmup_updates`` then fits that critic before the actor moves. Both refuse an
    ensemble, a corrupt file or one that is no policy with a CheckpointError naming ``path``."""
    import dataclasses

    from bimacppo_planner.policy import ENSEMBLE_FORMAT, POLICY_FORMAT, Policy, read_torch_file

    from .checkpoint import check_checkpoint, checkpoint_meta
    from .ppo import check_state_shapes

    d = read_torch_file(path)
    fmt = d.get("format") if isinstance(d, Mapping) else None
    if fmt == ENSEMBLE_FORMAT:
        raise CheckpointError(path, "is an ensemble of policies; fine-tune one of its members instead")
    if fmt != POLICY_FORMAT:
        d = check_checkpoint(d, path)
        try:
            pcfg, _ = config_from_dict(d["config"], source=str(path))
            agent = PPO(int(d["agent"]["obs_dim"]), list(d["agent"]["nvec"]), pcfg, seed=seed)
        except (ValueError, TypeError, KeyError) as exc:
            raise CheckpointError(path, f"cannot rebuild the agent: {exc}") from None
        restore_agent(agent, d["agent"], path)
        return agent, checkpoint_meta(d, path), False
    pol = Policy(d, path)          # refuses a malformed or non-finite export, naming path
    try:
        pcfg = dataclasses.replace(load_config()[0], hidden_sizes=pol.hidden_sizes,
                                   activation=pol.activation, obs_norm=pol.obs_norm)
        agent = PPO(pol.obs_dim, list(pol.nvec), pcfg, seed=seed)
        check_state_shapes("actor", agent.actor.state_dict(), d["actor"])
        agent.actor.load_state_dict(d["actor"])
        agent.obs_rms.load_state_dict(d["obs_rms"])
    except (ValueError, TypeError, KeyError, RuntimeError) as exc:
        raise CheckpointError(path, f"cannot rebuild the agent: {exc}") from None
    return agent, dict(pol.meta), True
