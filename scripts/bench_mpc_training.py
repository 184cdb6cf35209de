#!/usr/bin/env python3
"""The NMPC on the problems training gives it, not on the benchmark's tracking problems.

``bimacppo-mpc-bench`` times closed-loop tracking of smooth references. Training solves other
problems: every episode's new reference of the last decision, many far off the EV's path while
the policy explores. This script records them and replays them, so the two can be compared:

1. Record: a random policy drives ``--batch`` episodes of the batched training env
   (``IntersectionBatch``, extended env config, BiM-ACPPO's scenario mix) for ``--decisions``
   decisions; every (x0, x_ref, u_prev) handed to ``solve_batch`` is kept per slot, with the
   episode starts (where the warm start is forgotten).
2. Per problem: each slot's problems solved in order with ``solve()`` on one core, each call
   timed: mean, median, p90, p99, max; SQP iterations; the share of problems (and of the time)
   over 1 ms and in the second start; and the same split by reference: a problem whose
   reference is new (a decision's first tick, or an episode's first problem) against one that
   tracks the reference of the slot's previous problem (the decision's later ticks, where the
   shifted warm start already lies near the optimum).
3. Throughput: the recorded batches replayed through ``solve_batch`` on 1 and on 2 threads,
   ``--repeats`` pairs, median problems/s and the ratio; and the ratio on the batches of a
   decision's first tick (mostly new references) apart from the rest, whose solves are short
   enough that handing half of them to a second thread costs a visible share.

Prints figures; asserts nothing.

    .venv/bin/python scripts/bench_mpc_training.py                  # 300 decisions x 16 episodes
    .venv/bin/python scripts/bench_mpc_training.py --decisions 50   # a quick look
"""
from __future__ import annotations

import argparse
import pathlib
import resource
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
EXT = ROOT / "bimacppo_learning" / "bimacppo_learning" / "config" / "env_extended.yaml"


def record(batch_size: int, decisions: int, seed: int, env_config: str, mpc_config: str | None):
    """Problems per slot, in order: lists of (x0, x_ref, u_prev, new_episode) per slot, and the
    batches as (X0, Xref, Uprev, reset slots before it)."""
    from tqdm import tqdm

    from bimacppo_learning.batch import IntersectionBatch
    from bimacppo_mpc import MPCConfig
    from bimacppo_planner.decision import EnvConfig

    env = IntersectionBatch(batch_size, config=EnvConfig.load(env_config),
                            mpc_config=MPCConfig.load(mpc_config))
    per_slot = [[] for _ in range(batch_size)]
    batches = []
    fresh = set(range(batch_size))            # slots whose next problem starts an episode
    solve_batch, reset = env.ctrl.solve_batch, env.ctrl.reset

    def recording_solve_batch(X0, Xref, Uprev):
        batches.append((np.array(X0), np.array(Xref), np.array(Uprev), sorted(fresh)))
        for i in range(len(X0)):
            per_slot[i].append((np.array(X0[i]), np.array(Xref[i]), np.array(Uprev[i]), i in fresh))
        fresh.clear()
        return solve_batch(X0, Xref, Uprev)

    def recording_reset(slots=None):
        fresh.update(range(batch_size) if slots is None else np.atleast_1d(slots).tolist())
        return reset(slots)

    env.ctrl.solve_batch, env.ctrl.reset = recording_solve_batch, recording_reset
    rng = np.random.default_rng(seed)
    for i in range(batch_size):
        env.reset(i, seed=seed * 1000 + i)
    for _ in tqdm(range(decisions), desc="record", unit="decision", file=sys.stderr):
        actions = np.stack([rng.integers(0, n, size=batch_size) for n in env.nvec], axis=1)
        _, _, term, trunc, _ = env.step(actions)
        for i in np.nonzero(term | trunc)[0]:
            env.reset(int(i))
    return per_slot, batches, env.ctrl.cfg


def per_problem(cfg, per_slot):
    from tqdm import tqdm

    from bimacppo_mpc import make_controller

    ctrl = make_controller(cfg, "fast")
    ctrl.set_threads(1)
    x0, xr, up, _ = per_slot[0][0]
    ctrl.solve(x0, xr, up)                    # excluded: compilation and first allocation
    times, iters, starts = [], [], []
    total = sum(len(s) for s in per_slot)
    with tqdm(total=total, desc="solve() one by one", unit="problem", file=sys.stderr) as bar:
        for problems in per_slot:
            for x0, xr, up, new in problems:   # each slot's first problem starts an episode
                if new:
                    ctrl.reset()
                t0 = time.perf_counter()
                res = ctrl.solve(x0, xr, up)
                times.append(time.perf_counter() - t0)
                iters.append(res.iterations)
                starts.append(res.starts)
                bar.update(1)
    return np.array(times), np.array(iters), np.array(starts)


def new_reference(per_slot) -> np.ndarray:
    """Per problem, in ``per_problem``'s order: True where the slot's reference differs from the
    one of its previous problem, or the problem starts an episode (no warm start to shift)."""
    out = []
    for problems in per_slot:
        prev = None
        for _, xr, _, new in problems:
            out.append(new or prev is None or not np.array_equal(xr, prev))
            prev = xr
    return np.array(out, dtype=bool)


def split_rows(t: np.ndarray, it: np.ndarray, st: np.ndarray, new: np.ndarray) -> list[tuple[str, str]]:
    """Rows of the new- / same-reference split: share of problems and of the time, mean and median
    solve, mean SQP iterations, second starts."""
    rows = []
    total = t.sum()
    for name, m in (("new reference", new), ("same reference", ~new)):
        if not m.any():
            rows.append((f"{name}: no problems", "-"))
            continue
        us = t[m] * 1e6
        rows.append((f"{name}: share of problems / of time; mean / median [us]; SQP iterations; second starts",
                     f"{100 * m.mean():.1f} % / {100 * t[m].sum() / total:.1f} %; {us.mean():,.0f} / "
                     f"{np.median(us):,.0f}; {it[m].mean():.2f}; {100 * (st[m] == 2).mean():.1f} %"))
    return rows


def throughput(cfg, batches, threads: int) -> tuple[float, np.ndarray]:
    """Problems/s of the recorded batches replayed through solve_batch on ``threads`` threads,
    and each batch's wall time [s]."""
    from bimacppo_mpc import make_controller

    ctrl = make_controller(cfg, "fast")
    ctrl.set_threads(threads)
    X0, Xr, Up, _ = batches[0]
    ctrl.solve_batch(X0, Xr, Up)              # excluded: allocation of the slots, thread start
    ctrl.reset()
    walls = np.empty(len(batches))
    for k, (X0, Xr, Up, fresh) in enumerate(batches):
        if fresh:
            ctrl.reset(slots=fresh)
        t0 = time.perf_counter()
        ctrl.solve_batch(X0, Xr, Up)
        walls[k] = time.perf_counter() - t0
    return len(batches) * len(batches[0][0]) / walls.sum(), walls


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--decisions", type=int, default=300, help="decisions recorded (default 300)")
    ap.add_argument("--batch", type=int, default=16, help="episodes stepped together (default 16, as training)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--env-config", default=str(EXT), help="env config YAML (default: the extended config)")
    ap.add_argument("--mpc-config", default=None, help="MPC config YAML (default: the packaged mpc.yaml)")
    ap.add_argument("--repeats", type=int, default=3, help="1-thread / 2-thread throughput pairs (default 3)")
    a = ap.parse_args(argv)
    if a.decisions < 1 or a.batch < 1 or a.repeats < 1:
        ap.error("--decisions, --batch and --repeats must be >= 1")

    per_slot, batches, cfg = record(a.batch, a.decisions, a.seed, a.env_config, a.mpc_config)
    t, it, st = per_problem(cfg, per_slot)
    us = t * 1e6
    slow = t > 1e-3
    second = st == 2
    runs = [(throughput(cfg, batches, 1), throughput(cfg, batches, 2)) for _ in range(a.repeats)]
    pairs = [(r1[0], r2[0]) for r1, r2 in runs]
    one, two = np.median([p[0] for p in pairs]), np.median([p[1] for p in pairs])
    ratios = np.array([p[1] / p[0] for p in pairs])
    # batches where most slots start a new reference (a decision's first tick) against the rest:
    # the two threads' speed-up on each, from the summed wall times over the repeats
    new = new_reference(per_slot)
    first = new.reshape(a.batch, len(batches)).mean(axis=0) > 0.5
    w1 = np.sum([r1[1] for r1, _ in runs], axis=0)
    w2 = np.sum([r2[1] for _, r2 in runs], axis=0)
    by_kind = " / ".join(f"{w1[m].sum() / w2[m].sum():.2f}x ({1e6 * w1[m].mean() / a.repeats:,.0f} -> "
                         f"{1e6 * w2[m].mean() / a.repeats:,.0f} us)" if m.any() else "-"
                         for m in (first, ~first))
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0

    print(f"\nNMPC on training problems: {len(t):,} problems ({a.batch} episodes x {a.decisions} decisions, "
          f"random policy, seed {a.seed}, env config {pathlib.Path(a.env_config).name}, "
          f"MPC config {a.mpc_config or 'packaged mpc.yaml'})\n")
    rows = [
        ("solve() one by one, 1 thread [us]: mean / median / p90 / p99 / max",
         " / ".join(f"{v:,.0f}" for v in (us.mean(), *np.percentile(us, [50, 90, 99]), us.max()))),
        ("SQP iterations: mean / median / p99", f"{it.mean():.2f} / {np.median(it):.0f} / {np.percentile(it, 99):.0f}"),
        ("solves over 1 ms: share of problems / of time",
         f"{100 * slow.mean():.1f} % / {100 * t[slow].sum() / t.sum():.1f} %"),
        ("second start: share of problems / of time",
         f"{100 * second.mean():.1f} % / {100 * t[second].sum() / t.sum():.1f} %"),
        *split_rows(t, it, st, new),
        (f"solve_batch B={a.batch}: 1 / 2 threads [problems/s] (median of {a.repeats})", f"{one:,.0f} / {two:,.0f}"),
        ("ratio 2 threads / 1 thread: median (min-max)", f"{np.median(ratios):.2f}x ({ratios.min():.2f}-{ratios.max():.2f})"),
        ("ratio 2 / 1 threads on batches of mostly new references / the rest (mean wall per batch)", by_kind),
        ("peak RSS [MiB]", f"{rss:,.0f}"),
    ]
    w = max(len(r[0]) for r in rows)
    print(f"| {'figure'.ljust(w)} | value |\n|{'-' * (w + 2)}|---|")
    for name, val in rows:
        print(f"| {name.ljust(w)} | {val} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
