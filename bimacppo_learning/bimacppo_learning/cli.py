"""Command-line tools: ``bimacppo-train`` and ``bimacppo-evaluate``.

Training runs in-process (no ROS) on the same core code the nodes wrap; see docs/training.md.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any, Mapping

from bimacppo_common.conventions import TASKS
from bimacppo_curriculum import make_scheduler

from bimacppo_planner.decision import ConfigError, EnvConfig

from .seed_sets import SEED_SETS

CURRICULA = ("bimab", "fixed", "random", "manual", "rd")
MAPS = ("dual_lane_4way", "single_lane_4way", "three_lane_straight")


def make_env(map_id: str, env_config: EnvConfig, mpc_solver: str, slow_svs: int = 0, mpc_config=None,
             world_config=None):
    """The training env's picklable factory (one env when called, ``make_batch(n)`` for the
    batched vector env). Every curriculum draws all three tasks (its arms); a map with one task
    (the straight road has only "straight") runs it for every arm (``conventions.task_on_map``,
    the rule the ROS curriculum node follows too), and ``slow_svs`` > 0 slows up to that many SVs
    per episode (paper §IV-C overtaking, in ``batch.py``).
    ``mpc_config`` (an MPCConfig; None: the packaged mpc.yaml) is the NMPC under the planner,
    ``world_config`` (a WorldConfig; None: the packaged world.yaml) the world of the episodes."""
    from .vec_env import EnvFactory

    return EnvFactory(map_id, env_config, mpc_solver, slow_svs, mpc_config=mpc_config, world_config=world_config)


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
    p.add_argument("--num-envs", type=int, default=None, help="environments stepped together (default: config/ppo.yaml, 16); PPO updates on num_envs x rollout_steps samples, so change rollout_steps with it (--ppo-config)")
    p.add_argument("--vector", choices=("batched", "async", "sync"), default=None,
                   help="batched = all envs in this process, one NMPC and policy call per step (fastest); "
                        "async = one subprocess per env; sync = a plain in-process loop")
    p.add_argument("--ppo-config", type=Path, default=None, help="YAML overriding bimacppo_learning/config/ppo.yaml (with --init-policy: default the source checkpoint's PPO config; a given file applies in full; one that changes hidden_sizes, activation or obs_norm is refused)")
    p.add_argument("--env-config", type=Path, default=None,
                   help="YAML overlaying bimacppo_planner/config/env.yaml (lists only what it changes)")
    p.add_argument("--curriculum-config", default=None,
                   help="YAML for the scheduler (default: the packaged one for that curriculum)")
    p.add_argument("--init-policy", type=Path, default=None,
                   help="start from this training checkpoint (fine-tuning, e.g. overtaking), or from a policy "
                        "export, whose critic then starts untrained (see ppo.critic_warmup_updates)")
    p.add_argument("--fine-tune-reward", action="store_true",
                   help="with --init-policy: the fine-tune trains with the reward section of --env-config; "
                        "only observation and action must match the checkpoint's")
    p.add_argument("--fine-tune-action", action="store_true",
                   help="with --init-policy: the fine-tune decodes actions with the action section of "
                        "--env-config (e.g. action.lane_change_from); the action heads' sizes must still match")
    p.add_argument("--fine-tune-observation", action="store_true",
                   help="with --init-policy: the fine-tune may turn on observation features the checkpoint "
                        "lacks (observation.junction, observation.lanes; every other observation key must "
                        "match); their input weights start at zero, so it starts from the checkpoint's behaviour")
    p.add_argument("--fine-tune-lane-prior", type=float, default=None, metavar="P",
                   help="with --init-policy: the lane-change head (A3) starts keeping the lane with "
                        "probability P in every state, left and right (1 - P) / 2 each; its other "
                        "weights are dropped (docs/method.md, variant 24); default: the source's head")
    p.add_argument("--mpc", choices=("fast", "ipopt"), default="fast", help="NMPC solver in the loop")
    p.add_argument("--mpc-config", type=Path, default=None,
                   help="YAML overlaying bimacppo_mpc/config/mpc.yaml (lists only what it changes, e.g. "
                        "mpc_unbounded.yaml); recorded in the checkpoints and policy.pt, and --resume / "
                        "--init-policy need the one the checkpoint records; default: the packaged one")
    p.add_argument("--world-config", type=Path, default=None,
                   help="YAML overlaying bimacppo_sim/config/world.yaml for the training episodes only (e.g. "
                        "where and how fast the EV starts); recorded in run.json and policy.pt; evaluation "
                        "always runs the packaged world, so the test scenarios stay the same; default: packaged")
    p.add_argument("--slow-svs", type=int, default=0, metavar="N",
                   help="slow down 0..N SVs per episode (drawn from the reset seed), for overtaking "
                        "fine-tunes on three_lane_straight (paper: 2); default 0")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (logs only)")
    return p


def fail(prog: str, message: Any) -> int:
    """Report a refused command the way argparse's ``parser.error`` does (``prog: error: ...``,
    exit status 2), on one line and without the usage: the message says what to change."""
    print(f"{prog}: error: {' '.join(str(message).split())}", file=sys.stderr)
    return 2


def check_checkpoint_fits(path: Path, obs_dim: int, nvec, run_meta_: dict, env_cfg: EnvConfig,
                          mpc_cfg=None, sections=("observation", "action", "reward")) -> str | None:
    """Why a checkpoint cannot continue (--resume) or start (--init-policy) a run with ``env_cfg``
    and the NMPC ``mpc_cfg``: another observation or action size, another env config in one of
    ``sections`` (a checkpoint that records none was made with the packaged one, the rule
    deployment follows) or another MPC config (one that records none is of unknown controller:
    not compared, a warning); None if it fits. ``mpc_cfg`` None skips the MPC comparison. A
    resume compares every section (it continues one run); a fine-tune that says so
    (--fine-tune-reward) only what the policy sees and does, observation and action, because
    its reward is then the new task's to choose; one that says --fine-tune-action leaves the
    action section out too (the heads' sizes are compared whatever the sections), because how
    an action decodes is then also the new task's."""
    from .checkpoint import CheckpointError, config_differences, mpc_config_of

    if (int(obs_dim), tuple(int(n) for n in nvec)) != (env_cfg.obs_dim, tuple(env_cfg.nvec)):
        return (f"{path}: its agent takes observations of size {obs_dim} and actions nvec={list(nvec)}; "
                f"this run's env config gives {env_cfg.obs_dim} and {list(env_cfg.nvec)}: "
                "pass the --env-config it was trained with")
    raw = run_meta_.get("env_config")
    try:
        saved = EnvConfig.load() if raw is None else EnvConfig.from_dict(raw, where=f"{path} (run env_config)")
    except ConfigError as exc:
        return str(exc)
    diff = config_differences({k: v for k, v in saved.to_dict().items() if k in sections},
                              {k: v for k, v in env_cfg.to_dict().items() if k in sections})
    if diff:
        return (f"{path}: was trained with another env config ({'; '.join(diff)}; checkpoint != this run): "
                "pass the --env-config it was trained with")
    if mpc_cfg is None:
        return None
    try:
        saved_mpc = mpc_config_of(run_meta_, path)
    except CheckpointError as exc:
        return str(exc)
    if saved_mpc is None:
        logging.getLogger(__name__).warning(
            "%s records no MPC config (written before runs recorded theirs): its controller is unknown and "
            "not compared with this run's (%s)", path, mpc_cfg.source)
        return None
    diff = config_differences(saved_mpc.to_dict(), mpc_cfg.to_dict())
    if diff:
        return (f"{path}: was trained with another MPC config ({'; '.join(diff)}; checkpoint != this run): "
                "pass the --mpc-config it was trained with")
    return None


def widen_for(path: Path, agent, run_meta_: dict, env_cfg: EnvConfig):
    """(why not, agent) for a fine-tune whose observation turns on feature groups the checkpoint's
    lacks (``decision.observation_blocks``): every other observation key must match, and the
    agent's input layer is widened by the new groups with zero weights (``ppo.widen_inputs``).
    The agent is returned unchanged when the groups are the same."""
    from bimacppo_planner.decision import observation_blocks

    from .checkpoint import config_differences
    from .ppo import widen_inputs

    raw = run_meta_.get("env_config")
    try:
        saved = EnvConfig.load() if raw is None else EnvConfig.from_dict(raw, where=f"{path} (run env_config)")
    except ConfigError as exc:
        return str(exc), None
    old_blocks, new_blocks = observation_blocks(saved.observation), observation_blocks(env_cfg.observation)
    groups = {name for name, _ in new_blocks} - {name for name, _ in old_blocks}
    dropped = {name for name, _ in old_blocks} - {name for name, _ in new_blocks}
    if dropped:
        return (f"{path}: this run's observation leaves out the checkpoint's {', '.join(sorted(dropped))} "
                "features: a fine-tune can add observation features, not remove them"), None
    old_obs, new_obs = saved.to_dict()["observation"], env_cfg.to_dict()["observation"]
    for name in groups:
        old_obs[name] = new_obs[name]
    diff = config_differences({"observation": old_obs}, {"observation": new_obs})
    if diff:
        return (f"{path}: was trained with another observation ({'; '.join(diff)}; checkpoint != this run): "
                "--fine-tune-observation only turns feature groups on"), None
    if int(agent.obs_dim) != sum(size for _, size in old_blocks):
        return (f"{path}: its agent takes observations of size {agent.obs_dim}, but its env config gives "
                f"{sum(size for _, size in old_blocks)}"), None
    start, at = {}, 0
    for name, size in old_blocks:
        start[name] = at
        at += size
    columns = []
    for name, size in new_blocks:
        columns += [start[name] + k for k in range(size)] if name in start else [-1] * size
    if not groups:
        return None, agent
    return None, widen_inputs(agent, columns)


def _world_differs(path: Path, run_meta_: dict, world_cfg) -> str | None:
    """Why a run cannot be resumed in the training world ``world_cfg`` (None: the packaged
    world.yaml): its checkpoint records another one (none recorded = the packaged world)."""
    from bimacppo_sim import WorldConfig

    from .checkpoint import config_differences

    saved = run_meta_.get("world_config")
    if saved is None:
        saved = world_config_dict(WorldConfig.load())
    diff = config_differences(saved, world_config_dict(world_cfg or WorldConfig.load()))
    if diff:
        return (f"{path}: was trained in another world ({'; '.join(diff)}; checkpoint != this run): "
                "resume with the --world-config it was trained with")
    return None


def _preflight(args, env_cfg: EnvConfig, pcfg, run_dir: Path, mpc_cfg, world_cfg=None):
    """Every check a run can fail before it starts, so that a refused run leaves its directory as
    it was. Returns (error message or None, the --init-policy agent or None, the run's PPO config,
    the record of the file the weights descend from or None).

    A fine-tune (--init-policy) trains under its source's PPO config unless --ppo-config names
    one; the agent adopts the run's config, so what trains is what the checkpoints record. A
    resumed run's weights come from its checkpoint, so its lineage is the checkpoint's."""
    from .checkpoint import (CheckpointError, config_differences, fine_tune_source_record, latest_checkpoint,
                             load_checkpoint, run_meta_of)
    from .ppo_config import config_from_dict, config_to_dict
    from .trainer import load_fine_tune_source

    path = latest = latest_checkpoint(run_dir / "checkpoints")
    try:
        if latest is not None and not args.resume:
            return (f"{run_dir} already holds checkpoints ({latest.name}): pass --resume to continue it, "
                    "or give another --run-dir"), None, pcfg, None
        agent = source = None
        if args.init_policy is not None:
            path = args.init_policy
            agent, meta, fresh_critic = load_fine_tune_source(path, seed=args.seed)
            source = fine_tune_source_record(path, meta)
            if args.ppo_config is None:
                pcfg = agent.cfg
            else:
                diff = config_differences(config_to_dict(agent.cfg)["ppo"], config_to_dict(pcfg)["ppo"], "ppo")
                if diff:
                    logging.getLogger(__name__).info(
                        "the fine-tune trains under %s, not its source's PPO config (%s)",
                        args.ppo_config, "; ".join(diff))
                try:
                    agent.adopt_config(pcfg)
                except ValueError as exc:
                    return f"{path}: {exc}", None, pcfg, None
            widened = False
            if args.fine_tune_observation:
                why, agent = widen_for(path, agent, meta, env_cfg)
                if why:
                    return why, None, pcfg, None
                widened = True
            sections = tuple(name for name, free in (("observation", widened), ("action", args.fine_tune_action),
                                                     ("reward", args.fine_tune_reward)) if not free)
            why = check_checkpoint_fits(path, agent.obs_dim, agent.nvec, meta, env_cfg, mpc_cfg, sections)
            if why and not args.fine_tune_reward and "reward." in why:
                why += " (--fine-tune-reward lets a fine-tune change the reward)"
            if why and not args.fine_tune_action and "action." in why:
                why += " (--fine-tune-action lets a fine-tune change how actions decode)"
            if why:
                return why, None, pcfg, None
            if args.fine_tune_lane_prior is not None:
                from bimacppo_planner.decision import LANE_CHANGE_HEAD

                from .ppo import set_head_prior

                keep = args.fine_tune_lane_prior
                sides = env_cfg.action.lane_change
                set_head_prior(agent, LANE_CHANGE_HEAD,
                               [keep if side == 0 else (1.0 - keep) / (len(sides) - 1) for side in sides])
            if fresh_critic and pcfg.critic_warmup_updates == 0:
                logging.getLogger(__name__).warning(
                    "%s is a policy export: the critic starts untrained and ppo.critic_warmup_updates is 0, "
                    "so the first updates move the actor along an untrained critic's advantages", path)
        path = latest
        if args.resume and latest is not None:
            d = load_checkpoint(latest)
            saved_meta = run_meta_of(d, latest)
            source = saved_meta.get("fine_tuned_from")
            why = check_checkpoint_fits(latest, d["agent"]["obs_dim"], d["agent"]["nvec"], saved_meta, env_cfg,
                                        mpc_cfg)
            if why:
                return why, None, pcfg, None
            try:
                saved_pcfg, _ = config_from_dict(d["config"], source=str(latest))
            except ValueError as exc:
                return f"{latest}: config is invalid: {exc}", None, pcfg, None
            diff = config_differences(config_to_dict(saved_pcfg)["ppo"], config_to_dict(pcfg)["ppo"], "ppo")
            if diff:
                return (f"{latest}: was trained with another PPO config ({'; '.join(diff)}; checkpoint != "
                        "this run): resume with the same ppo section"), None, pcfg, None
            why = _world_differs(latest, saved_meta, world_cfg)
            if why:
                return why, None, pcfg, None
    except CheckpointError as exc:
        return str(exc), None, pcfg, None
    except (KeyError, TypeError, ValueError) as exc:
        return f"{path}: malformed checkpoint ({type(exc).__name__}: {exc})", None, pcfg, None
    return None, agent, pcfg, source


def train_main(argv=None) -> int:
    args = _train_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from bimacppo_mpc import MPCConfig
    from bimacppo_sim import WorldConfig

    from .checkpoint import CheckpointError
    from .ppo_config import load_config
    from .trainer import Trainer

    prog = "bimacppo-train"
    if args.episodes < 1:
        return fail(prog, f"--episodes must be >= 1, got {args.episodes}")
    if not 0 <= args.slow_svs <= 3:
        return fail(prog, f"--slow-svs must be in 0..3 (at most N_sv^max SVs), got {args.slow_svs}")
    if args.fine_tune_reward and args.init_policy is None:
        return fail(prog, "--fine-tune-reward needs --init-policy (a resume keeps its run's reward)")
    if args.fine_tune_observation and args.init_policy is None:
        return fail(prog, "--fine-tune-observation needs --init-policy (a resume keeps its run's observation)")
    if args.fine_tune_action and args.init_policy is None:
        return fail(prog, "--fine-tune-action needs --init-policy (a resume keeps its run's action decoding)")
    if args.fine_tune_lane_prior is not None:
        if args.init_policy is None:
            return fail(prog, "--fine-tune-lane-prior needs --init-policy (it sets a fine-tune's starting A3 head)")
        if not 0.0 < args.fine_tune_lane_prior < 1.0:
            return fail(prog, f"--fine-tune-lane-prior must be a probability in (0, 1), got {args.fine_tune_lane_prior}")
    try:
        env_cfg = EnvConfig.load(args.env_config)
        mpc_cfg = MPCConfig.load(args.mpc_config)
        world_cfg = None if args.world_config is None else WorldConfig.load(args.world_config)
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
        return fail(prog, exc)
    run_dir = args.run_dir or Path("runs") / f"{args.curriculum}-s{args.seed}"
    why, agent, pcfg, source = _preflight(args, env_cfg, pcfg, run_dir, mpc_cfg, world_cfg)
    if why:
        return fail(prog, why)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "run.json").write_text(json.dumps({
        "curriculum": args.curriculum, "episodes": args.episodes, "seed": args.seed, "map": args.map,
        "mpc": args.mpc, "slow_svs": args.slow_svs, "env_config": env_cfg.to_dict(),
        "mpc_config": mpc_cfg.to_dict(), "argv": sys.argv[1:] if argv is None else list(argv),
        **({} if world_cfg is None else {"world_config": world_config_dict(world_cfg)}),
        **({} if source is None else {"fine_tuned_from": source}),
    }, indent=2))
    env_fn = make_env(args.map, env_cfg, args.mpc, args.slow_svs, mpc_config=mpc_cfg, world_config=world_cfg)
    from bimacppo_sim import load_map

    tasks = list(load_map(args.map).tasks)
    if len(tasks) < 3:
        print(f"bimacppo-train: map {args.map!r} has only the task(s) {tasks}: the curriculum's task "
              "arms all run as that task (its arm statistics are then not meaningful)", file=sys.stderr)
    trainer = Trainer(env_fn, sched, run_dir, pcfg, tcfg, agent=agent,
                      run_meta=run_meta(env_cfg, args.curriculum, args.map, args.seed, args.mpc, mpc_cfg,
                                        world_cfg, fine_tuned_from=source))
    try:
        res = trainer.train(args.episodes, resume=args.resume)
    except CheckpointError as exc:
        return fail(prog, exc)
    print(f"trained {res.episodes} episodes ({res.env_steps} steps, {res.updates} updates); "
          f"success over the last {tcfg.success_window}: {100 * res.success_rate:.1f}%")
    tm = res.timing
    other = tm["total"] - tm["env"] - tm["policy"] - tm["update"]
    print(f"time: {tm['total']:.1f} s = env {tm['env']:.1f} + policy {tm['policy']:.1f} + "
          f"PPO update {tm['update']:.1f} + bookkeeping {other:.1f}")
    print(cpu_line(tm))
    print(f"policy: {run_dir / 'policy.pt'}   history: {res.history_path}   checkpoint: {res.last_checkpoint}")
    return 0


def cpu_line(tm: Mapping[str, float]) -> str:
    """The call's CPU seconds split like its time: this process, every thread, so what the work
    costs the machine, which wall time on several cores hides (env worker processes not included)."""
    other = tm["total_cpu"] - tm["env_cpu"] - tm["policy_cpu"] - tm["update_cpu"]
    nmpc = f" (NMPC {tm['mpc_cpu_seconds']:.1f})" if "mpc_cpu_seconds" in tm else ""
    return (f"CPU: {tm['total_cpu']:.1f} s = env {tm['env_cpu']:.1f}{nmpc} + policy {tm['policy_cpu']:.1f} + "
            f"PPO update {tm['update_cpu']:.1f} + bookkeeping {other:.1f} (this process, every thread)")


def world_config_dict(world_cfg) -> dict:
    from bimacppo_common import config as common_config

    return common_config.to_dict(world_cfg)


def run_meta(env_cfg: EnvConfig, curriculum: str, map_id: str, seed: int, mpc: str, mpc_cfg=None,
             world_cfg=None, fine_tuned_from: dict | None = None) -> dict:
    """How a run was trained, as stored in its checkpoints and exported policy (Trainer.run_meta):
    deployment (planner node, evaluation) rebuilds the same observation and decoding from it, and
    evaluation runs the NMPC it was trained with (``mpc_cfg``; None: the packaged mpc.yaml, what
    the env then runs). A training world other than the packaged one (``world_cfg``) is recorded
    for the record only: evaluation never uses it, so every policy meets the same scenarios.
    ``fine_tuned_from`` (``checkpoint.fine_tune_source_record``) is the file a fine-tune's
    weights started from, with that file's own lineage."""
    if mpc_cfg is None:
        from bimacppo_mpc import MPCConfig

        mpc_cfg = MPCConfig.load()
    meta = {"env_config": env_cfg.to_dict(), "mpc_config": mpc_cfg.to_dict(), "curriculum": curriculum,
            "map": map_id, "seed": seed, "mpc": mpc}
    if world_cfg is not None:
        meta["world_config"] = world_config_dict(world_cfg)
    if fine_tuned_from is not None:
        meta["fine_tuned_from"] = dict(fine_tuned_from)
    return meta


def add_protocol_arguments(p: argparse.ArgumentParser, *, episodes: int, episodes_help: str,
                           n_svs: list[int]) -> None:
    """The evaluation protocol's cell options (map, episodes, N_sv, tasks, workers, slow SVs), shared
    by every command that runs ``evaluate``; ``protocol_tasks`` checks them."""
    p.add_argument("--map", default="dual_lane_4way", choices=MAPS)
    p.add_argument("--episodes", type=int, default=episodes, help=episodes_help)
    p.add_argument("--n-sv", type=int, nargs="+", default=list(n_svs))
    p.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    p.add_argument("--workers", type=int, default=2, help="processes (cells run in parallel)")
    p.add_argument("--slow-svs", type=int, default=0, metavar="N",
                   help="slow down 0..N SVs per episode, drawn from the scenario seed as in training's --slow-svs "
                        "(the overtaking tests on three_lane_straight: --map three_lane_straight --tasks straight "
                        "--n-sv 3 --slow-svs 2); default 0")


def protocol_tasks(args: argparse.Namespace) -> list[int]:
    """The task indices of ``add_protocol_arguments``' options, after checking them all
    (ValueError with a one-line message naming the option)."""
    from .evaluate import check_cells

    if not 1 <= args.episodes <= 1000:
        raise ValueError(f"--episodes must be in 1..1000, got {args.episodes}")
    if args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    if args.slow_svs < 0:
        raise ValueError(f"--slow-svs must be >= 0, got {args.slow_svs}")
    tasks = [TASKS.index(t) for t in args.tasks]
    try:
        check_cells(args.map, args.n_sv, tasks)
    except ValueError as exc:
        raise ValueError(f"{exc}: choose --n-sv / --tasks within it") from None
    return tasks


def _eval_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="bimacppo-evaluate",
        description="The paper's evaluation protocol: every task x N_sv cell, N episodes on fixed "
                    "scenario seeds shared by all methods; prints the S/C/TO table (markdown), with a "
                    "uniform random policy's row on the same scenarios under each task, and writes CSV.")
    p.add_argument("policy", nargs="?", default=None,
                   help="policy.pt export or training checkpoint (default: the shipped policy)")
    add_protocol_arguments(p, episodes=100, episodes_help="episodes per cell, 1..1000 (paper: 100)",
                           n_svs=[0, 1, 2, 3])
    p.add_argument("--mpc", choices=("fast", "ipopt"), default="fast")
    p.add_argument("--env-config", type=Path, default=None,
                   help="YAML replacing the env config stored in the policy file (default: that one)")
    p.add_argument("--no-random-row", action="store_true", help="skip the random-policy baseline rows")
    p.add_argument("--mpc-config", type=Path, default=None,
                   help="YAML overlaying bimacppo_mpc/config/mpc.yaml (e.g. mpc_unbounded.yaml for a policy "
                        "trained without the rate bounds); default: the one the policy file records, else "
                        "the packaged one")
    p.add_argument("--seed-set", choices=sorted(SEED_SETS), default="test",
                   help="scenario seeds: validation (for choosing configs, checkpoints, variants) or test "
                        "(reporting only); validation2 / test2 are a second pair for a choice made afresh; "
                        "disjoint sets, default test")
    from bimacppo_planner.policy import ACTION_SELECTIONS

    p.add_argument("--action", choices=ACTION_SELECTIONS, default=None,
                   help="how a policy file picks each head's action (default: the way the file records, else "
                        "argmax): argmax, median (the head's "
                        "weighted median over its ordered values, deterministic) or sample (the policy as "
                        "trained, seeded per episode by --sample-seed and the scenario seed)")
    p.add_argument("--sample", action="store_true", help="the same as --action sample")
    p.add_argument("--sample-seed", type=int, default=0, help="seed of --sample's action draws")
    p.add_argument("--out", type=Path, default=None,
                   help="write OUT.md (the table), OUT.csv (the policy's cells) and OUT_random.csv")
    p.add_argument("--title", default="")
    return p


def evaluate_main(argv=None) -> int:
    args = _eval_parser().parse_args(argv)
    from .checkpoint import CheckpointError
    from .evaluate import (EvaluationError, default_selection, evaluate, resolve_mpc_config, resolve_policy,
                           to_markdown, write_outputs)

    prog = "bimacppo-evaluate"
    try:
        tasks = protocol_tasks(args)
    except ValueError as exc:
        return fail(prog, exc)
    if args.sample and args.action not in (None, "sample"):
        return fail(prog, f"--sample contradicts --action {args.action}")
    selection = "sample" if args.sample else args.action
    try:   # fail fast, in this process, with a clear message
        spec, loaded, _ = resolve_policy(args.policy, args.env_config)
    except (CheckpointError, EvaluationError, ConfigError) as exc:
        return fail(prog, exc)
    from tqdm.auto import tqdm

    n_cells = len(tasks) * len(args.n_sv) * (1 if args.no_random_row else 2)
    bar = tqdm(total=n_cells, unit="cell", desc="evaluating", disable=None)

    def progress(cell):
        bar.update(1)
        who = "random " if cell.policy == "random" else ""
        bar.set_postfix_str(f"{who}{TASKS[cell.task]} N_sv={cell.n_sv}: S={cell.pct('success'):.0f}%")

    try:
        results = evaluate(args.policy, args.map, args.n_sv, tasks, args.episodes, args.workers, args.mpc,
                           progress, env_config=args.env_config, random_row=not args.no_random_row,
                           seed_set=args.seed_set, mpc_config=args.mpc_config,
                           action_selection=selection, sample_seed=args.sample_seed,
                           slow_svs=args.slow_svs)
    except (CheckpointError, EvaluationError, ConfigError) as exc:
        return fail(prog, exc)
    finally:
        bar.close()
    title = args.title
    selection = selection or default_selection(spec, loaded)
    if selection != "argmax":
        what = f"actions sampled (seed {args.sample_seed})" if selection == "sample" else "median actions"
        title = (f"{title}: " if title else "") + what
    notes = [_nmpc_note(resolve_mpc_config(loaded, args.mpc_config))]
    print(to_markdown(results, title, notes))
    if args.out:
        md, cs = write_outputs(results, args.out, title, notes)
        print(f"wrote {md} and {cs}")
    return 0


def _nmpc_note(cfg) -> str:
    """Which NMPC the cells ran: evaluation follows the policy's record, so say it."""
    from bimacppo_mpc.config import DEFAULT_PATH

    if cfg is None:
        return f"NMPC: {DEFAULT_PATH} (packaged; the policy records none)"
    f = cfg.fast
    return (f"NMPC: {cfg.source} (fast.second_start_cut: {f.second_start_cut}, "
            f"fast.steer_bound_other_side: {f.steer_bound_other_side})")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(train_main())
