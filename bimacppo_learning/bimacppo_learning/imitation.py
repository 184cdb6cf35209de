"""Behaviour-cloned warm start for the PPO planner (an extension beyond the paper).

Why: PPO with any of the curricula plateaus at ~75-80 % success at N_sv = 3 (docs/results.md):
it never learns to *wait* before the junction, although the action space allows it (WP0 at
0 m/s holds the EV) and the scripted "yield" driver succeeds everywhere. Here that driver's
rule is expressed in the planner's own action space (the *teacher*: it sees the world, i.e.
every SV's true state), its decisions are recorded against the planner's *observation*, and
the actor is fitted to them by cross-entropy (the critic to the teacher's Monte-Carlo
returns). The result is a training checkpoint for ``bimacppo-train --init-policy``, so the
PPO + BiMAB training of the paper starts from a policy that already yields, plus an exported
policy for ``bimacppo-evaluate`` and the planner node.

``bimacppo-imitate --env-config ... --out-dir runs/bc`` writes ``checkpoint.pt``,
``policy.pt`` and ``imitation.json`` (teacher outcomes, clone accuracy).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
import dataclasses
from pathlib import Path
from typing import Callable

import numpy as np

from bimacppo_common import config
from bimacppo_common.config import ConfigError, Packaged, config_class, invalid, runtime, setting
from bimacppo_planner.decision import EnvConfig

log = logging.getLogger(__name__)
IMITATION_YAML = Packaged("bimacppo_learning", "config/imitation.yaml")
DEFAULT_CONFIG = Path(IMITATION_YAML.path)
TASK_NAMES = ("left", "straight", "right")


@config_class(IMITATION_YAML, "teacher")
class TeacherConfig:
    go: dict[str, tuple[int, ...]] = setting(keys=TASK_NAMES, length=3, lo=0)   # task -> [A1, A2, A3]
    stop: tuple[int, ...] = setting(length=3, lo=0)
    commit_margin: float = setting(lo=0.0, hi=50.0)
    brake_decel: float = setting(lo=0.1, hi=10.0)
    brake_within: float = setting(lo=0.0, hi=50.0)


@config_class(IMITATION_YAML, "clone")
class CloneConfig:
    epochs: int = setting(lo=1, hi=10_000)
    batch_size: int = setting(lo=1, hi=1_000_000)
    lr: float = setting(lo=1e-7, hi=1.0)
    gamma: float = setting(lo=0.0, hi=1.0)


@config_class(IMITATION_YAML)
class ImitationConfig:
    episodes: int = setting(lo=1, hi=10_000_000)
    seed_base: int = setting(lo=0, hi=2**62)
    n_sv_probs: tuple[float, ...] = setting(lo=0.0, min_length=1)
    teacher: TeacherConfig
    clone: CloneConfig
    source: str = runtime("")     # the file it was read from

    def _check(self) -> None:
        if abs(sum(self.n_sv_probs) - 1.0) > 1e-6:
            raise invalid("n_sv_probs", f"must be non-negative numbers summing to 1, got {list(self.n_sv_probs)}")

    @classmethod
    def load(cls, path: str | Path | None = None, nvec=None) -> "ImitationConfig":
        """The packaged imitation.yaml, overlaid by the YAML at ``path`` (which lists only what it
        changes); ``nvec`` (the env's action sizes) bounds the teacher's actions."""
        cfg = config.load(cls, path)
        cfg = dataclasses.replace(cfg, source=str(path) if path is not None else IMITATION_YAML.path)
        if nvec is not None:
            actions = {f"teacher.go.{k}": v for k, v in cfg.teacher.go.items()}
            actions["teacher.stop"] = cfg.teacher.stop
            for key, a in actions.items():
                if not all(0 <= x < n for x, n in zip(a, nvec)):
                    raise ConfigError(f"must be [A1, A2, A3] within MultiDiscrete({list(nvec)}), got {list(a)}",
                                      source=cfg.source, key=key)
        return cfg


class YieldTeacher:
    """The scripted "yield" rule (bimacppo_sim.drivers: its threat test and stop line)
    acting through the planner's action space, so that its decisions can be cloned."""

    def __init__(self, env, cfg: TeacherConfig):
        self.env, self.cfg = env, cfg
        self._drv = None
        self.committed = False
        self.go = None

    def reset(self) -> None:
        from bimacppo_sim.config import DriverConfig

        self._drv = DriverConfig.load()
        self.committed = False
        self.go = np.array(self.cfg.go[self.env.scenario.task])

    def act(self) -> np.ndarray:
        if self._drv is None:
            raise RuntimeError("YieldTeacher.act() before reset()")
        from bimacppo_sim.drivers import junction_threatened, stop_line_distance

        c = self.cfg
        if self.committed or getattr(self.env.road, "H", None) is None:
            return self.go
        _, y, v, _ = self.env.world.ego_tuple()
        d = stop_line_distance(self.env.world, self._drv, y)
        if not junction_threatened(self.env.world, self._drv):
            if d <= c.commit_margin:
                self.committed = True
            return self.go
        braking = v * v >= 2.0 * c.brake_decel * max(d - 1.0, 0.01) * 0.8
        if d > 0.0 and not braking and d >= c.brake_within:
            return self.go
        return np.array(c.stop)


def collect(env, cfg: ImitationConfig, seed: int = 0, progress: Callable | None = None):
    """Teacher rollouts: observations, actions, discounted returns, outcome counts."""
    rng = np.random.default_rng(seed)
    teacher = YieldTeacher(env, cfg.teacher)
    O, A, R, outcomes = [], [], [], {}
    ntask = len(env.tasks)
    for k in range(cfg.episodes):
        n_sv = int(rng.choice(len(cfg.n_sv_probs), p=cfg.n_sv_probs))
        task = env.tasks[int(rng.integers(ntask))]
        obs, _ = env.reset(options={"n_sv": min(n_sv, env.max_sv), "task": task,
                                    "scenario_seed": cfg.seed_base + k})
        teacher.reset()
        rews = []
        while True:
            a = teacher.act()
            O.append(obs)
            A.append(a)
            obs, r, term, trunc, info = env.step(a)
            rews.append(r)
            if term or trunc:
                break
        g, ret = 0.0, []
        for r in reversed(rews):
            g = r + cfg.clone.gamma * g
            ret.append(g)
        R.extend(reversed(ret))
        outcomes[info["outcome"]] = outcomes.get(info["outcome"], 0) + 1
        if progress:
            progress(info["outcome"])
    return (np.asarray(O, np.float32), np.asarray(A, np.int64), np.asarray(R, np.float32), outcomes)


def behaviour_clone(agent, O, A, R, cfg: CloneConfig, seed: int = 0, progress: Callable | None = None) -> dict:
    """Fit the actor to the teacher's actions (cross-entropy over the three heads) and the
    critic to its returns (MSE); the observation normaliser is set from the data first, as
    PPO would have after seeing it. Returns the final loss and the data-set accuracy."""
    import torch

    agent.obs_rms.update(O)
    X = torch.as_tensor(agent.normalize_obs(O))
    Aa, Rt = torch.as_tensor(A), torch.as_tensor(R)
    opt_a = torch.optim.Adam(agent.actor.parameters(), lr=cfg.lr)
    opt_c = torch.optim.Adam(agent.critic.parameters(), lr=cfg.lr)
    g = torch.Generator().manual_seed(int(seed))
    ce = vl = float("nan")
    for _ in range(cfg.epochs):
        perm = torch.randperm(len(X), generator=g)
        tot_ce = tot_v = 0.0
        for i in range(0, len(X), cfg.batch_size):
            idx = perm[i:i + cfg.batch_size]
            loss = -agent.dist(X[idx]).log_prob(Aa[idx]).mean()
            opt_a.zero_grad(set_to_none=True)
            loss.backward()
            opt_a.step()
            lv = ((agent.critic(X[idx]).squeeze(-1) - Rt[idx]) ** 2).mean()
            opt_c.zero_grad(set_to_none=True)
            lv.backward()
            opt_c.step()
            tot_ce += float(loss.detach()) * len(idx)
            tot_v += float(lv.detach()) * len(idx)
        ce, vl = tot_ce / len(X), tot_v / len(X)
        if progress:
            progress(ce)
    with torch.no_grad():
        acc = float((agent.dist(X).mode() == Aa).all(-1).float().mean())
    return {"cross_entropy": ce, "value_mse": vl, "accuracy": acc, "samples": int(len(X))}


def checkpoint_payload(agent, pcfg, tcfg, meta: dict | None = None) -> dict:
    """A training checkpoint (trainer format) holding only the agent: what ``--init-policy`` reads.
    ``meta`` is how the clone was made (env and MPC config, ...), stored as a run's metadata so
    that ``--init-policy`` checks it like a training checkpoint's."""
    import torch

    from .checkpoint import CHECKPOINT_FORMAT, FORMAT_VERSION
    from .ppo_config import config_to_dict

    return {"format": CHECKPOINT_FORMAT, "version": FORMAT_VERSION, "agent": agent.state_dict(),
            "config": config_to_dict(pcfg, tcfg), "scheduler_state": json.dumps({}),
            "counters": {"episodes": 0, "env_steps": 0, "updates": 0},
            "rng": {"episode_rng": np.random.default_rng(0).bit_generator.state, "torch": torch.get_rng_state()},
            "success_window": [], "run": json.dumps(dict(meta or {}))}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="bimacppo-imitate",
        description="Behaviour-clone the scripted 'yield' teacher into a PPO agent: a warm start "
                    "for `bimacppo-train --init-policy <out-dir>/checkpoint.pt`.")
    p.add_argument("--out-dir", type=Path, required=True)
    p.add_argument("--env-config", type=Path, default=None, help="the env config PPO will train with")
    p.add_argument("--config", type=Path, default=None, help=f"default: {DEFAULT_CONFIG.name} (packaged)")
    p.add_argument("--ppo-config", type=Path, default=None, help="network sizes etc. (default: packaged ppo.yaml)")
    p.add_argument("--map", default="dual_lane_4way")
    p.add_argument("--episodes", type=int, default=None, help="override the config's teacher episodes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--mpc", choices=("fast", "ipopt"), default="fast")
    p.add_argument("--mpc-config", type=Path, default=None,
                   help="YAML overlaying bimacppo_mpc/config/mpc.yaml: the NMPC the teacher drives through "
                        "(and PPO will train with), recorded in the outputs; default: the packaged one")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    import torch
    from bimacppo_mpc import MPCConfig
    from tqdm.auto import tqdm

    from .checkpoint import export_policy, save_checkpoint
    from .env import IntersectionEnv
    from .ppo import PPO
    from .ppo_config import load_config

    try:
        env_cfg = EnvConfig.load(args.env_config)
        cfg = ImitationConfig.load(args.config, nvec=env_cfg.nvec)
        if args.episodes is not None:
            if args.episodes < 1:
                raise ConfigError("--episodes must be >= 1")
            cfg = ImitationConfig(args.episodes, cfg.seed_base, cfg.n_sv_probs, cfg.teacher, cfg.clone, cfg.source)
        pcfg, tcfg = load_config(args.ppo_config, train={"seed": args.seed})
        mpc_cfg = MPCConfig.load(args.mpc_config)
        env = IntersectionEnv(map_id=args.map, config=env_cfg, mpc_solver=args.mpc, mpc_config=mpc_cfg)
    except (ConfigError, ValueError, OSError) as exc:
        print(f"bimacppo-imitate: {exc}", file=sys.stderr)
        return 2
    if getattr(env.road, "H", None) is None:
        print(f"bimacppo-imitate: map {args.map!r} has no junction to yield at", file=sys.stderr)
        return 2
    args.out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)
    t0 = time.time()
    bar = tqdm(total=cfg.episodes, unit="ep", desc="teacher", disable=args.no_progress or None)
    O, A, R, outcomes = collect(env, cfg, seed=args.seed, progress=lambda o: bar.update(1))
    bar.close()
    t_collect = time.time() - t0
    agent = PPO(env_cfg.obs_dim, env_cfg.nvec, pcfg, seed=args.seed)
    bar = tqdm(total=cfg.clone.epochs, unit="epoch", desc="clone", disable=args.no_progress or None)
    stats = behaviour_clone(agent, O, A, R, cfg.clone, seed=args.seed,
                            progress=lambda ce: (bar.update(1), bar.set_postfix(ce=f"{ce:.3f}")))
    bar.close()
    ckpt = args.out_dir / "checkpoint.pt"
    meta = {"env_config": env_cfg.to_dict(), "mpc_config": mpc_cfg.to_dict(), "curriculum": "imitation",
            "map": args.map, "seed": args.seed, "mpc": args.mpc}
    save_checkpoint(ckpt, checkpoint_payload(agent, pcfg, tcfg, meta))
    export_policy(agent, args.out_dir / "policy.pt", meta=meta)
    report = {"teacher_outcomes": outcomes, "episodes": cfg.episodes, **stats, "collect_s": round(t_collect, 1),
              "total_s": round(time.time() - t0, 1), "config": cfg.source, "seed": args.seed, "map": args.map}
    (args.out_dir / "imitation.json").write_text(json.dumps(report, indent=2))
    n = max(1, sum(outcomes.values()))
    print(f"teacher: {outcomes} ({100 * outcomes.get('success', 0) / n:.1f}% success) over {cfg.episodes} episodes; "
          f"clone accuracy {100 * stats['accuracy']:.1f}% on {stats['samples']} decisions")
    print(f"checkpoint (for bimacppo-train --init-policy): {ckpt}\npolicy: {args.out_dir / 'policy.pt'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
