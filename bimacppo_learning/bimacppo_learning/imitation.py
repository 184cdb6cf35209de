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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from bimacppo_planner.decision import ConfigError, EnvConfig

log = logging.getLogger(__name__)
DEFAULT_CONFIG = Path(__file__).parent / "config" / "imitation.yaml"
TASK_NAMES = ("left", "straight", "right")


@dataclass(frozen=True)
class TeacherConfig:
    go: dict = field(default_factory=dict)      # task -> [A1, A2, A3]
    stop: tuple = (0, 0, 1)
    commit_margin: float = 3.0
    brake_decel: float = 2.5
    brake_within: float = 4.0


@dataclass(frozen=True)
class CloneConfig:
    epochs: int = 40
    batch_size: int = 512
    lr: float = 1e-3
    gamma: float = 0.99


@dataclass(frozen=True)
class ImitationConfig:
    episodes: int
    seed_base: int
    n_sv_probs: tuple
    teacher: TeacherConfig
    clone: CloneConfig
    source: str = ""

    @classmethod
    def load(cls, path: str | Path | None = None, nvec=None) -> "ImitationConfig":
        """Read and validate the YAML; ``nvec`` (the env's action sizes) bounds the actions."""
        p = Path(path) if path is not None else DEFAULT_CONFIG
        try:
            d = yaml.safe_load(p.read_text())
        except OSError as exc:
            raise ConfigError(f"{p}: cannot read ({exc.strerror or exc})") from None
        except yaml.YAMLError as exc:
            raise ConfigError(f"{p}: not valid YAML ({str(exc).splitlines()[0]})") from None
        if not isinstance(d, dict):
            raise ConfigError(f"{p}: top level must be a mapping")

        def need(m, key, where, kind, lo=None, hi=None):
            if not isinstance(m, dict) or key not in m:
                raise ConfigError(f"{p}: missing key '{where}{key}'")
            v = m[key]
            if kind is int and (isinstance(v, bool) or not isinstance(v, int)):
                raise ConfigError(f"{p}: key '{where}{key}' must be an integer, got {v!r}")
            if kind is float:
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                    raise ConfigError(f"{p}: key '{where}{key}' must be a finite number, got {v!r}")
                v = float(v)
            if (lo is not None and v < lo) or (hi is not None and v > hi):
                raise ConfigError(f"{p}: key '{where}{key}' = {v} outside [{lo}, {hi}]")
            return v

        def action(v, where):
            ok = isinstance(v, list) and len(v) == 3 and all(isinstance(a, int) and not isinstance(a, bool) for a in v)
            if ok and nvec is not None:
                ok = all(0 <= a < n for a, n in zip(v, nvec))
            if not ok:
                raise ConfigError(f"{p}: key '{where}' must be [A1, A2, A3] within MultiDiscrete({list(nvec or [])}), "
                                  f"got {v!r}")
            return tuple(v)

        probs = d.get("n_sv_probs")
        if (not isinstance(probs, list) or not probs or
                not all(isinstance(x, (int, float)) and not isinstance(x, bool) and x >= 0 for x in probs) or
                abs(sum(probs) - 1.0) > 1e-6):
            raise ConfigError(f"{p}: key 'n_sv_probs' must be non-negative numbers summing to 1, got {probs!r}")
        t = d.get("teacher")
        go = need(t, "go", "teacher.", dict)
        if not isinstance(go, dict) or set(go) != set(TASK_NAMES):
            raise ConfigError(f"{p}: key 'teacher.go' must map exactly {list(TASK_NAMES)} to actions")
        teacher = TeacherConfig(
            go={k: action(v, f"teacher.go.{k}") for k, v in go.items()},
            stop=action(need(t, "stop", "teacher.", list), "teacher.stop"),
            commit_margin=need(t, "commit_margin", "teacher.", float, 0.0, 50.0),
            brake_decel=need(t, "brake_decel", "teacher.", float, 0.1, 10.0),
            brake_within=need(t, "brake_within", "teacher.", float, 0.0, 50.0))
        c = d.get("clone")
        clone = CloneConfig(epochs=need(c, "epochs", "clone.", int, 1, 10_000),
                            batch_size=need(c, "batch_size", "clone.", int, 1, 1_000_000),
                            lr=need(c, "lr", "clone.", float, 1e-7, 1.0),
                            gamma=need(c, "gamma", "clone.", float, 0.0, 1.0))
        return cls(episodes=need(d, "episodes", "", int, 1, 10_000_000),
                   seed_base=need(d, "seed_base", "", int, 0, 2**62),
                   n_sv_probs=tuple(float(x) for x in probs), teacher=teacher, clone=clone, source=str(p))


class YieldTeacher:
    """The scripted "yield" rule (bimacppo_sim.drivers.YieldDriver: threat test, stop line)
    acting through the planner's action space, so that its decisions can be cloned."""

    def __init__(self, env, cfg: TeacherConfig):
        self.env, self.cfg = env, cfg
        self._yd = None
        self.committed = False
        self.go = None

    def reset(self) -> None:
        from bimacppo_sim.drivers import YieldDriver

        self._yd = YieldDriver(self.env.world)
        self.committed = False
        self.go = np.array(self.cfg.go[self.env.scenario.task])

    def act(self) -> np.ndarray:
        if self._yd is None:
            raise RuntimeError("YieldTeacher.act() before reset()")
        c = self.cfg
        if self.committed or getattr(self.env.road, "H", None) is None:
            return self.go
        _, y, v, _ = self.env.world.ego_tuple()
        d = self._yd._stop_distance(y)
        if not self._yd._threat():
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


def checkpoint_payload(agent, pcfg, tcfg) -> dict:
    """A training checkpoint (trainer format) holding only the agent: what ``--init-policy`` reads."""
    import torch

    from .checkpoint import CHECKPOINT_FORMAT, FORMAT_VERSION
    from .ppo_config import config_to_dict

    return {"format": CHECKPOINT_FORMAT, "version": FORMAT_VERSION, "agent": agent.state_dict(),
            "config": config_to_dict(pcfg, tcfg), "scheduler_state": json.dumps({}),
            "counters": {"episodes": 0, "env_steps": 0, "updates": 0},
            "rng": {"episode_rng": np.random.default_rng(0).bit_generator.state, "torch": torch.get_rng_state()},
            "success_window": []}


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
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    import torch
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
        env = IntersectionEnv(map_id=args.map, config=env_cfg, mpc_solver=args.mpc)
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
    save_checkpoint(ckpt, checkpoint_payload(agent, pcfg, tcfg))
    meta = {"env_config": env_cfg.to_dict(), "curriculum": "imitation", "map": args.map, "seed": args.seed,
            "mpc": args.mpc}
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
