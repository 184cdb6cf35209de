"""Command-line tools: ``bimacppo-train`` and ``bimacppo-evaluate``.

Training runs in-process (no ROS) on the same core code the nodes wrap; see docs/training.md.
"""
from __future__ import annotations

import argparse
import functools
import json
import logging
import sys
from pathlib import Path

from bimacppo_curriculum import SCHEDULERS, make_scheduler

from bimacppo_planner.decision import ConfigError, EnvConfig

CURRICULA = ("bimab", "fixed", "random", "manual", "rd")
MAPS = ("dual_lane_4way", "single_lane_4way", "three_lane_straight")


def make_env(map_id: str, env_config: EnvConfig, mpc_solver: str, slow_svs: int = 0):
    """The training env's picklable factory (one env when called, ``make_batch(n)`` for the
    batched vector env). Every curriculum draws all three tasks (its arms); a map with fewer (the
    straight road has only "straight") folds them onto its own, and ``slow_svs`` > 0 slows up to
    that many SVs per episode (paper §IV-C overtaking): both rules live in ``batch.py``."""
    from .vec_env import EnvFactory

    return EnvFactory(map_id, env_config, mpc_solver, slow_svs)


def _train_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="bimacppo-train",
        description="Train the BiM-ACPPO planner (PPO over NMPC) with a curriculum. Writes "
                    "history.jsonl, TensorBoard logs (tb/), checkpoints/ and policy.pt to --run-dir.")
    p.add_argument("--curriculum", choices=CURRICULA, default="bimab",
                   help="bimab = BiM-ACPPO; fixed = Fixed PPO; random = Random CPPO; manual = Manual CPPO; rd = RD-ACPPO")
    p.add_argument("--episodes", type=int, default=5000, help="episode budget (paper: ~5000)")
    p.add_argument("--seed", type=int, default=0, help="training seed (network init, curriculum, scenarios)")
    p.add_argument("--map", default="dual_lane_4way", choices=MAPS)
    p.add_argument("--run-dir", type=Path, default=None, help="default: runs/<curriculum>-s<seed>")
    p.add_argument("--resume", action="store_true", help="continue from the latest checkpoint in --run-dir")
    p.add_argument("--num-envs", type=int, default=None, help="parallel environments (default: config, 2)")
    p.add_argument("--vector", choices=("batched", "async", "sync"), default=None,
                   help="batched = all envs in this process, one NMPC and policy call per step (fastest); "
                        "async = one subprocess per env; sync = a plain in-process loop")
    p.add_argument("--ppo-config", type=Path, default=None, help="YAML overriding bimacppo_learning/config/ppo.yaml")
    p.add_argument("--env-config", type=Path, default=None, help="YAML replacing bimacppo_planner/config/env.yaml")
    p.add_argument("--curriculum-config", default=None,
                   help="YAML for the scheduler (default: the packaged one for that curriculum)")
    p.add_argument("--init-policy", type=Path, default=None,
                   help="start from this training checkpoint (fine-tuning, e.g. overtaking)")
    p.add_argument("--mpc", choices=("fast", "ipopt"), default="fast", help="NMPC solver in the loop")
    p.add_argument("--slow-svs", type=int, default=0, metavar="N",
                   help="slow down 0..N SVs per episode (drawn from the reset seed), for overtaking "
                        "fine-tunes on three_lane_straight (paper: 2); default 0")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (logs only)")
    return p


def train_main(argv=None) -> int:
    args = _train_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from .ppo_config import load_config
    from .trainer import Trainer, load_agent

    if args.episodes < 1:
        print("bimacppo-train: --episodes must be >= 1", file=sys.stderr)
        return 2
    if not 0 <= args.slow_svs <= 3:
        print(f"bimacppo-train: --slow-svs must be in 0..3 (at most N_sv^max SVs), got {args.slow_svs}",
              file=sys.stderr)
        return 2
    try:
        env_cfg = EnvConfig.load(args.env_config)
        train_over = {"seed": args.seed}
        if args.num_envs is not None:
            train_over["num_envs"] = args.num_envs
        if args.vector is not None:
            train_over["vector"] = args.vector
        if args.no_progress:
            train_over["progress_bar"] = False
        pcfg, tcfg = load_config(args.ppo_config, train=train_over)
        sched = make_scheduler(args.curriculum, seed=args.seed, total_episodes=args.episodes,
                               config=args.curriculum_config)
    except (ConfigError, ValueError, OSError) as exc:
        print(f"bimacppo-train: {exc}", file=sys.stderr)
        return 2
    run_dir = args.run_dir or Path("runs") / f"{args.curriculum}-s{args.seed}"
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "run.json").write_text(json.dumps({
        "curriculum": args.curriculum, "episodes": args.episodes, "seed": args.seed, "map": args.map,
        "mpc": args.mpc, "slow_svs": args.slow_svs, "env_config": env_cfg.to_dict(), "argv": sys.argv[1:] if argv is None else list(argv),
    }, indent=2))
    agent = load_agent(args.init_policy) if args.init_policy else None
    env_fn = make_env(args.map, env_cfg, args.mpc, args.slow_svs)
    from bimacppo_sim import load_map

    tasks = sorted(load_map(args.map).turns)
    if len(tasks) < 3:
        print(f"bimacppo-train: map {args.map!r} has only the task(s) {tasks}: the curriculum's task "
              "arms all run as that task (its arm statistics are then not meaningful)", file=sys.stderr)
    trainer = Trainer(env_fn, sched, run_dir, pcfg, tcfg, agent=agent,
                      run_meta=run_meta(env_cfg, args.curriculum, args.map, args.seed, args.mpc))
    res = trainer.train(args.episodes, resume=args.resume)
    print(f"trained {res.episodes} episodes ({res.env_steps} steps, {res.updates} updates); "
          f"success over the last {tcfg.success_window}: {100 * res.success_rate:.1f}%")
    tm = res.timing
    other = tm["total"] - tm["env"] - tm["policy"] - tm["update"]
    print(f"time: {tm['total']:.1f} s = env {tm['env']:.1f} + policy {tm['policy']:.1f} + "
          f"PPO update {tm['update']:.1f} + bookkeeping {other:.1f}")
    print(f"policy: {run_dir / 'policy.pt'}   history: {res.history_path}   checkpoint: {res.last_checkpoint}")
    return 0


def run_meta(env_cfg: EnvConfig, curriculum: str, map_id: str, seed: int, mpc: str) -> dict:
    """How a run was trained, as stored in its checkpoints and exported policy (Trainer.run_meta):
    deployment (planner node, evaluation) rebuilds the same observation and decoding from it."""
    return {"env_config": env_cfg.to_dict(), "curriculum": curriculum, "map": map_id, "seed": seed, "mpc": mpc}


def _eval_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="bimacppo-evaluate",
        description="The paper's evaluation protocol: every task x N_sv cell, N episodes on fixed "
                    "scenario seeds shared by all methods; prints the S/C/TO table (markdown) and writes CSV.")
    p.add_argument("policy", nargs="?", default=None,
                   help="policy.pt export or training checkpoint (default: the shipped policy)")
    p.add_argument("--map", default="dual_lane_4way", choices=MAPS)
    p.add_argument("--episodes", type=int, default=100, help="episodes per cell (paper: 100)")
    p.add_argument("--n-sv", type=int, nargs="+", default=[0, 1, 2, 3])
    p.add_argument("--tasks", nargs="+", default=["left", "straight", "right"],
                   choices=["left", "straight", "right"])
    p.add_argument("--workers", type=int, default=2, help="processes (cells run in parallel)")
    p.add_argument("--mpc", choices=("fast", "ipopt"), default="fast")
    p.add_argument("--out", type=Path, default=None, help="write OUT.md and OUT.csv")
    p.add_argument("--title", default="")
    return p


def evaluate_main(argv=None) -> int:
    args = _eval_parser().parse_args(argv)
    from bimacppo_sim import TASKS

    from bimacppo_planner.agent import load_policy
    from .checkpoint import CheckpointError
    from .evaluate import evaluate, to_markdown, write_outputs

    try:
        load_policy(args.policy)   # fail fast, in this process, with a clear message
    except CheckpointError as exc:
        print(f"bimacppo-evaluate: {exc}", file=sys.stderr)
        return 2
    if not 1 <= args.episodes <= 1000:
        print("bimacppo-evaluate: --episodes must be in 1..1000", file=sys.stderr)
        return 2
    tasks = [TASKS.index(t) for t in args.tasks]
    from tqdm.auto import tqdm

    bar = tqdm(total=len(tasks) * len(args.n_sv), unit="cell", desc="evaluating")

    def progress(cell):
        bar.update(1)
        bar.set_postfix_str(f"{TASKS[cell.task]} N_sv={cell.n_sv}: S={cell.pct('success'):.0f}%")

    results = evaluate(args.policy, args.map, args.n_sv, tasks, args.episodes, args.workers, args.mpc, progress)
    bar.close()
    print(to_markdown(results, args.title))
    if args.out:
        md, cs = write_outputs(results, args.out, args.title)
        print(f"wrote {md} and {cs}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(train_main())
