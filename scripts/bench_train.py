#!/usr/bin/env python3
"""Training throughput: the per-env subprocess path and the batched path, side by side, one run.

Each configuration trains BiM-ACPPO from scratch for the same number of episodes, same seed and
env config (default: the extended config), in a fresh child process, and
the table prints episodes/s, world ticks/s, decisions/s, the time split (env stepping, policy
forward, PPO update, bookkeeping), peak memory, and each row's ratio to the first row. Prints
figures; asserts nothing. Numbers on a shared machine are noisy: repeat with --repeat.

Each row also prints its CPU time per episode (every thread of the run's process and of its env
worker processes) and the ceiling that sets: the episodes/s of every core busy with that work, which
no scheduling of the same work can beat. The closing line says what ``--target-ratio`` times the
first row (default 10) asks of the CPU per episode on this machine, beside what the last row spends.

``--ref REF`` adds a row (first in the table, so the ratios are to it) that runs commit REF's own
``bimacppo-train`` exactly as a user ran it then: the commit's tree is exported from this
repository's git history to a temporary folder, its packages go first on PYTHONPATH, and its
console script trains with its packaged defaults (TensorBoard and all), ``--no-progress`` and the
commit's own copy of the env config (found by the file name of ``--env-config``). One untimed
episode first fills that tree's numba cache, as the installed packages' is. ``--ref HEAD`` runs
today's CLI the same way. Such a row has no time split (the CLI prints none).

``--concurrent N`` starts N copies of each configuration at once, as a sweep does on one machine:
the row shows one copy's figures (the median copy) and the aggregate episodes/s of all N.
``--omp-wait active`` runs the children with OMP_WAIT_POLICY=ACTIVE (OpenMP threads spin after
each parallel NMPC call) instead of the package's default, passive (bimacppo_common/__init__.py).
``--omp-spin N`` lets them spin for N iterations and then sleep (OMP_WAIT_POLICY=ACTIVE with
GOMP_SPINCOUNT=N): long enough to bridge the gap between a decision's NMPC calls, short enough to
sleep through the PPO update. ``--mpc-threads K`` runs every configuration's NMPC batch on K
threads (fast.threads; 0 = one per core, the packaged default), e.g. one per copy when two copies
share two cores.

    .venv/bin/python scripts/bench_train.py --episodes 500
    .venv/bin/python scripts/bench_train.py --episodes 600 --only batched --concurrent 2 --omp-wait active
    .venv/bin/python scripts/bench_train.py --episodes 500 --only batched --omp-spin 50000
    .venv/bin/python scripts/bench_train.py --episodes 500 --only batched --concurrent 2 --mpc-threads 1
    .venv/bin/python scripts/bench_train.py --episodes 5000 --only batched     # a full paper-budget run
    .venv/bin/python scripts/bench_train.py --episodes 500 --ref 34d3ac2 --ref HEAD --only batched
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import pathlib
import re
import subprocess
import sys
import tarfile
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[1]
EXT = ROOT / "bimacppo_learning" / "bimacppo_learning" / "config" / "env_extended.yaml"
# name -> train-section overrides; "per-env" is the loop as it ran before batching (2 subprocess
# envs x 1024 steps per update, every torch op on one thread); "batched" keeps 2048 samples per
# update (16 x 128), in this process or split over 2 worker processes. All rows run the update's
# operators on one thread (on a machine shared with other jobs, extra operator threads can cost
# more than they give); the batched rows fit the critic on a second thread beside the actor
# (train.critic_thread), "batched-serial-update" fits both on one.
BATCHED = {"vector": "batched", "num_envs": 16, "rollout_steps": 128, "batch_workers": 1, "update_threads": 1}
CONFIGS = {
    "per-env": {"vector": "async", "num_envs": 2, "rollout_steps": 1024, "update_threads": 1, "critic_thread": False},
    "batched": BATCHED,
    "batched-2proc": {**BATCHED, "batch_workers": 2},
    "batched-uncut": BATCHED,
    "batched-serial-update": {**BATCHED, "critic_thread": False},
}
# name -> overrides of the packaged mpc.yaml: "batched-uncut" is config/mpc_uncut.yaml, the solver
# as it was before the cut and the side rule of the second start (every second start that passes
# the gate runs, to convergence)
MPC = {"batched-uncut": {"fast": {"second_start_cut": None, "steer_bound_other_side": False}}}

# both children start here: the CPU time of this process (every thread) and of its reaped children
# (env worker processes), so a row can say what its work per episode costs the machine
CLOCK = r"""
import json, resource, sys, time


def cpu_now():
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime
"""

CHILD = r"""
from bimacppo_curriculum import make_scheduler
from bimacppo_learning.cli import make_env
from bimacppo_learning.ppo_config import load_config
from bimacppo_learning.trainer import Trainer
from bimacppo_mpc import MPCConfig
from bimacppo_planner.decision import EnvConfig
args = json.loads(sys.argv[1])
env_cfg = EnvConfig.load(args["env_config"])
pcfg, tcfg = load_config(train={**args["train"], "seed": args["seed"], "progress_bar": False, "tensorboard": False})
sched = make_scheduler("bimab", seed=args["seed"], total_episodes=args["episodes"])
t0, c0 = time.perf_counter(), cpu_now()
mpc = MPCConfig.load().replace(**args["mpc"])
res = Trainer(make_env("dual_lane_4way", env_cfg, "fast", mpc_config=mpc), sched, args["run_dir"], pcfg, tcfg).train(args["episodes"])
wall = time.perf_counter() - t0
recs = [json.loads(l) for l in open(res.history_path)]
episodes, decisions, timing = res.episodes, res.env_steps, res.timing
# processes stepping the envs (1: this one)
workers = {"batched": tcfg.batch_workers, "async": tcfg.num_envs}.get(tcfg.vector, 1)
"""

# a commit's own trainer CLI: imports happen before the clock starts, as in CHILD
REF_CHILD = r"""
import importlib
args = json.loads(sys.argv[1])
module, func = args["entry"].split(":")
main = getattr(importlib.import_module(module), func)
t0, c0 = time.perf_counter(), cpu_now()
rc = main(args["argv"])
wall = time.perf_counter() - t0
if rc:
    sys.exit(f"the trainer exited with {rc}")
recs = [json.loads(l) for l in open(args["history"])]
episodes, decisions, timing, workers = len(recs), recs[-1]["env_steps"] if recs else 0, None, None
"""
# both children end here: the RESULT line from the run's history (ticks only where every record has them)
RESULT = r"""
last = recs[-200:]
print("RESULT " + json.dumps({"wall": wall, "cpu": cpu_now() - c0, "workers": workers, "episodes": episodes, "decisions": decisions,
                             "ticks": sum(r["ticks"] for r in recs) if all("ticks" in r for r in recs) else None,
                             "timing": timing, "success": sum(r["outcome"] == "success" for r in last) / max(1, len(last)),
                             "rss_main_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                             "rss_worker_mib": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}))
"""
TRAIN_SCRIPT = re.compile(r"[\"']bimacppo-train\s*=\s*([\w.]+:\w+)")


class RefError(Exception):
    """A --ref that cannot be run (not a commit, no trainer CLI, no such env config)."""


def export_ref(ref: str, dest: pathlib.Path, root: pathlib.Path = ROOT) -> str:
    """Write commit ``ref``'s tree into ``dest`` (from git history: the working tree is not
    touched); returns the commit's short hash."""
    rev = subprocess.run(["git", "-C", str(root), "rev-parse", "--verify", "--short", f"{ref}^{{commit}}"],
                         capture_output=True, text=True)
    if rev.returncode != 0:
        raise RefError(f"--ref {ref}: not a commit of {root}")
    with tempfile.TemporaryFile() as tar:
        subprocess.run(["git", "-C", str(root), "archive", "--format=tar", rev.stdout.strip()], stdout=tar, check=True)
        tar.seek(0)
        with tarfile.open(fileobj=tar) as tf:
            tf.extractall(dest, filter="data")
    return rev.stdout.strip()


def ref_layout(tree: pathlib.Path, env_config: str) -> tuple[list[str], str, str]:
    """An exported tree's package folders (top-level ``D`` holding the package ``D/D``), its
    ``bimacppo-train`` entry point (module:function, from its setup.py files) and its own copy
    of the env config named like ``env_config``."""
    paths = sorted(str(d) for d in tree.iterdir() if (d / d.name / "__init__.py").is_file())
    entry = None
    for setup in sorted(tree.glob("*/setup.py")):
        m = TRAIN_SCRIPT.search(setup.read_text())
        if m:
            entry = m.group(1)
            break
    if entry is None:
        raise RefError(f"{tree.name}: no package declares the bimacppo-train console script")
    name = pathlib.Path(env_config).name
    found = sorted(tree.glob(f"*/*/config/{name}"))
    if not found:
        raise RefError(f"{tree.name}: has no config/{name} (the env config the other rows use)")
    return paths, entry, str(found[0])


def run_ref(ref: str, episodes: int, seed: int, env_config: str, copies: int = 1,
            omp_wait: str | None = None, omp_spin: int | None = None, root: pathlib.Path = ROOT) -> list[dict]:
    """``copies`` runs of commit ``ref``'s own trainer CLI started together; one result each."""
    with tempfile.TemporaryDirectory(prefix="bench-ref-") as tmp:
        tree = pathlib.Path(tmp) / "tree"
        commit = export_ref(ref, tree, root)
        paths, entry, cfg = ref_layout(tree, env_config)
        env = child_env(omp_wait, omp_spin)
        env["PYTHONPATH"] = os.pathsep.join(paths + [p for p in [os.environ.get("PYTHONPATH")] if p])

        def start(run_dir: str, n: int) -> subprocess.Popen:
            arg = json.dumps({"entry": entry, "history": os.path.join(run_dir, "history.jsonl"),
                              "argv": ["--episodes", str(n), "--seed", str(seed), "--env-config", cfg,
                                       "--run-dir", run_dir, "--no-progress"]})
            return subprocess.Popen([sys.executable, "-c", CLOCK + REF_CHILD + RESULT, arg], stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True, env=env, cwd=tmp)

        collect(f"{ref} (warm-up)", [start(os.path.join(tmp, "warm"), 1)])
        results = collect(ref, [start(os.path.join(tmp, str(c)), episodes) for c in range(copies)])
    return [dict(r, commit=commit) for r in results]


def collect(name: str, procs: list) -> list[dict]:
    """Wait for the children; the RESULT line of each, or exit naming the failed one."""
    outs = [(p, *p.communicate()) for p in procs]
    results = []
    for p, stdout, stderr in outs:
        line = next((l for l in stdout.splitlines() if l.startswith("RESULT ")), None)
        if p.returncode != 0 or line is None:
            raise SystemExit(f"bench_train: {name} failed (exit {p.returncode}): {stderr.strip()[-1500:]}")
        results.append(json.loads(line[len("RESULT "):]))
    return results


def child_env(omp_wait: str | None = None, omp_spin: int | None = None) -> dict:
    """The children's environment: progress bars off, and the OpenMP wait policy asked for
    (``omp_spin``: spin that many iterations, then sleep)."""
    env = {**os.environ, "TQDM_DISABLE": "1"}
    if omp_wait is not None:
        env["OMP_WAIT_POLICY"] = omp_wait.upper()
    if omp_spin is not None:
        env["OMP_WAIT_POLICY"] = "ACTIVE"
        env["GOMP_SPINCOUNT"] = str(omp_spin)
    return env


def mpc_overrides(name: str, mpc_threads: int | None = None) -> dict:
    """Configuration ``name``'s overrides of the packaged mpc.yaml, with ``fast.threads`` set
    where ``mpc_threads`` is given."""
    over = copy.deepcopy(MPC.get(name, {}))
    if mpc_threads is not None:
        over.setdefault("fast", {})["threads"] = mpc_threads
    return over


def run_many(name: str, episodes: int, seed: int, env_config: str, copies: int = 1,
             omp_wait: str | None = None, omp_spin: int | None = None,
             mpc_threads: int | None = None) -> list[dict]:
    """``copies`` children of configuration ``name`` started together; one result each."""
    env = child_env(omp_wait, omp_spin)
    with tempfile.TemporaryDirectory(prefix=f"bench-{name}-") as tmp:
        procs = []
        for c in range(copies):
            arg = json.dumps({"train": CONFIGS[name], "mpc": mpc_overrides(name, mpc_threads), "episodes": episodes, "seed": seed,
                              "env_config": env_config, "run_dir": os.path.join(tmp, str(c))})
            procs.append(subprocess.Popen([sys.executable, "-c", CLOCK + CHILD + RESULT, arg], stdout=subprocess.PIPE,
                                          stderr=subprocess.PIPE, text=True, env=env))
        return collect(name, procs)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=1, help="runs per configuration (the table shows the median)")
    ap.add_argument("--only", choices=sorted(CONFIGS), action="append", help="run only these configurations")
    ap.add_argument("--env-config", default=str(EXT))
    ap.add_argument("--concurrent", type=int, default=1, help="copies of each configuration run at once (a sweep on one machine)")
    ap.add_argument("--omp-wait", choices=("active", "passive"), default=None,
                    help="OMP_WAIT_POLICY of the children (default: the package's, passive)")
    ap.add_argument("--omp-spin", type=int, default=None, metavar="N",
                    help="idle OpenMP threads spin N iterations, then sleep (OMP_WAIT_POLICY=ACTIVE, GOMP_SPINCOUNT=N)")
    ap.add_argument("--mpc-threads", type=int, default=None, metavar="K",
                    help="threads of every configuration's NMPC batch (fast.threads; 0 = one per core)")
    ap.add_argument("--target-ratio", type=float, default=10.0, metavar="X",
                    help="the closing line says what X times the first row's episodes/s asks of the CPU (default 10)")
    ap.add_argument("--ref", action="append", default=[], metavar="REF",
                    help="also run commit REF's own bimacppo-train with its defaults (first rows; with --ref the configurations run only where --only names them)")
    args = ap.parse_args()
    if not 1 <= args.concurrent <= 64:
        ap.error(f"--concurrent must be in 1..64, got {args.concurrent}")
    if args.omp_spin is not None:
        if args.omp_spin < 0:
            ap.error(f"--omp-spin must be >= 0, got {args.omp_spin}")
        if args.omp_wait == "passive":
            ap.error("--omp-spin sets OMP_WAIT_POLICY=ACTIVE; it cannot go with --omp-wait passive")
    if not args.target_ratio > 0.0:
        ap.error(f"--target-ratio must be > 0, got {args.target_ratio}")
    if args.mpc_threads is not None and args.mpc_threads < 0:
        ap.error(f"--mpc-threads must be >= 0, got {args.mpc_threads}")
    names = [("ref", r) for r in args.ref] + [("config", n) for n in (args.only or ([] if args.ref else list(CONFIGS)))]
    rows = []
    for kind, name in names:
        runs = []
        for k in range(args.repeat):
            print(f"{name}: run {k + 1}/{args.repeat}, {args.episodes} episodes ...", file=sys.stderr, flush=True)
            if kind == "ref":
                try:
                    copies = run_ref(name, args.episodes, args.seed, args.env_config, args.concurrent,
                                     args.omp_wait, args.omp_spin)
                except RefError as exc:
                    ap.error(str(exc))
            else:
                copies = run_many(name, args.episodes, args.seed, args.env_config, args.concurrent, args.omp_wait,
                                  args.omp_spin, args.mpc_threads)
            one = sorted(copies, key=lambda r: r["wall"])[len(copies) // 2]
            one["aggregate"] = sum(r["episodes"] / r["wall"] for r in copies)
            runs.append(one)
        mid = sorted(runs, key=lambda r: r["wall"])[len(runs) // 2]
        mid["eps_all"] = [r["episodes"] / r["wall"] for r in runs]
        rows.append((kind, name, mid))
    base = rows[0][2]
    wait = ("active, GOMP_SPINCOUNT " + str(args.omp_spin) if args.omp_spin is not None
            else args.omp_wait or os.environ.get("OMP_WAIT_POLICY") or "passive (package default)")
    threads = "" if args.mpc_threads is None else f", NMPC threads {args.mpc_threads}"
    cores = os.cpu_count() or 1
    print(f"\n{args.episodes} episodes of BiM-ACPPO training from scratch, seed {args.seed}, "
          f"env config {pathlib.Path(args.env_config).name}, {cores} cores; median of {args.repeat}; "
          f"{args.concurrent} cop{'y' if args.concurrent == 1 else 'ies'} at once, OMP_WAIT_POLICY {wait}{threads}\n")
    print("| path | train config (and NMPC overrides) | episodes/s | all copies: episodes/s | ticks/s | decisions/s | ratio | "
          f"CPU ms per episode (every thread and worker) | ceiling on {cores} cores: episodes/s | "
          "CPU ms per episode: NMPC / rest of env / policy / update / other (in-process rows) | env s | "
          "of which NMPC s (solve_batch time, summed over processes) | "
          "NMPC per problem: µs of solve_batch wall time / SQP iterations / second starts | "
          "policy s | update s | other s | peak RSS main / largest worker (MiB) | success, last 200 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for kind, name, r in rows:
        print(table_row(kind, name, r, base, args.mpc_threads, cores))
    print("\n" + target_line(base, rows[-1][2], args.target_ratio, cores))
    return 0


def cpu_per_episode(r: dict) -> float:
    """Seconds of CPU (all threads of the run's process and of its env workers) per episode."""
    return r["cpu"] / r["episodes"]


def cpu_split(r: dict) -> dict | None:
    """A row's CPU seconds per episode by part (NMPC, the rest of env stepping, policy forward, PPO
    update, other: set-up, bookkeeping), where the whole run is in one process (the trainer times
    the parts in its own process, so worker processes' CPU would land in no part)."""
    tm = r.get("timing")
    if not tm or "total_cpu" not in tm or "mpc_cpu_seconds" not in tm or r.get("workers") != 1:
        return None
    n = r["episodes"]
    parts = {"nmpc": tm["mpc_cpu_seconds"], "env": tm["env_cpu"] - tm["mpc_cpu_seconds"],
             "policy": tm["policy_cpu"], "update": tm["update_cpu"]}
    parts["other"] = r["cpu"] - sum(parts.values())
    return {k: v / n for k, v in parts.items()}


def target_line(base: dict, last: dict, ratio: float, cores: int) -> str:
    """What ``ratio`` times the first row's episodes/s asks of the CPU, beside what the last row
    spends: the ceiling is the rate at which ``cores`` fully busy cores finish episodes of a row's
    work, so no scheduling of that work beats it."""
    want = ratio * base["episodes"] / base["wall"]
    budget = cores / want
    have = cpu_per_episode(last)
    split = cpu_split(last)
    fixed = ("" if split is None else
             f"; its NMPC and PPO update alone spend {1e3 * (split['nmpc'] + split['update']):.1f} ms "
             f"({(split['nmpc'] + split['update']) / budget:.2f}x the budget)")
    return (f"{ratio:g}x the first row is {want:.1f} episodes/s: on {cores} cores at most {1e3 * budget:.1f} ms of CPU "
            f"per episode; the last row spends {1e3 * have:.1f} ms ({have / budget:.2f}x that), so its ceiling is "
            f"{cores / have:.1f} episodes/s, {cores / have / (base['episodes'] / base['wall']):.2f}x the first row{fixed}")


def table_row(kind: str, name: str, r: dict, base: dict, mpc_threads: int | None = None, cores: int = 1) -> str:
    """One markdown row; a --ref row (``kind`` "ref") has no time split, and no ticks where its
    history does not record them."""
    tm = r["timing"]
    eps = r["episodes"] / r["wall"]
    spread = f" ({min(r['eps_all']):.1f}-{max(r['eps_all']):.1f})" if len(r["eps_all"]) > 1 else ""
    ticks = f"{r['ticks'] / r['wall']:.0f}" if r["ticks"] is not None else "-"
    if tm is None:
        split = "| - | - | - | - | - | -"
    else:
        other = tm["total"] - tm["env"] - tm["policy"] - tm["update"]
        mpc = f"{tm['mpc_seconds']:.1f}" if "mpc_seconds" in tm else "-"
        n = tm.get("mpc_problems", 0)
        per = (f"{1e6 * tm['mpc_seconds'] / n:.0f} / {tm['mpc_iterations'] / n:.2f} / {100 * tm['mpc_second_starts'] / n:.1f} %"
               if n else "-")
        split = f"| {tm['env']:.1f} | {mpc} | {per} | {tm['policy']:.1f} | {tm['update']:.1f} | {other:.1f}"
    if kind == "ref":
        at = name if r.get("commit", name).startswith(name) else f"{name} = {r['commit']}"
        label, conf = f"bimacppo-train at {at}", "the commit's own CLI and packaged defaults"
    else:
        over = mpc_overrides(name, mpc_threads)
        label, conf = name, json.dumps(CONFIGS[name]) + (f" NMPC {json.dumps(over)}" if over else "")
    parts = cpu_split(r)
    parts = "-" if parts is None else " / ".join(f"{1e3 * parts[k]:.1f}" for k in ("nmpc", "env", "policy", "update", "other"))
    return (f"| {label} | {conf} | {eps:.1f}{spread} | {r['aggregate']:.1f} | {ticks} | "
            f"{r['decisions'] / r['wall']:.0f} | {eps / (base['episodes'] / base['wall']):.2f}x | "
            f"{1e3 * cpu_per_episode(r):.1f} | {cores / cpu_per_episode(r):.1f} | {parts} {split} | "
            f"{r['rss_main_mib']:.0f} / {r['rss_worker_mib']:.0f} | {100 * r['success']:.0f}% |")


if __name__ == "__main__":
    sys.exit(main())
