"""Benchmark of the two solver configurations on closed-loop tracking problems.

1. Problems: the fast controller drives the bicycle model in closed loop from varied
   start states along intersection-like routes (straight, left or right quarter circle),
   tracking planner-like references that change every few steps; every control step
   gives one recorded problem (x0, x_ref, u_prev). Settings: config/bench.yaml.
2. Both configurations then solve every recorded problem, episode by episode (warm
   starts as in closed loop, ``reset()`` at each episode start), timing each call.
3. solve_batch throughput for several batch sizes, one episode per batch slot, on one
   thread and on all of numba's threads (the ratio is the parallel speed-up). Each pair of
   runs is repeated ``batch_repeats`` times, one and all threads back to back, and the table
   gives the median and the range: a single pass of a few hundred milliseconds moves by tens
   of per cent when anything else wakes up on the machine.

    python -m bimacppo_mpc.bench [--episodes E] [--repeats R] [--out results.md]

Timings are wall-clock on a shared machine: treat them as indicative.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import pathlib
import platform
import sys
import time
from dataclasses import dataclass
from typing import List

import numpy as np
import yaml

from . import _kernels as K
from .config import CONFIG_DIR, MPCConfig
from .controller import make_controller, pack_params

BENCH_PATH = CONFIG_DIR / "bench.yaml"


@dataclass(frozen=True)
class BenchConfig:
    seed: int
    episodes: int
    steps: int
    approach_length: float
    exit_length: float
    turn_radius: tuple
    route_kinds: tuple
    waypoint_spacing: float
    lookahead: tuple
    ref_speeds: tuple
    ref_hold_steps: tuple
    start_speed: tuple
    start_lateral_offset: float
    start_heading_error: float
    batch_sizes: tuple
    batch_steps: int
    batch_repeats: int

    @classmethod
    def load(cls, path=None) -> "BenchConfig":
        path = pathlib.Path(path) if path is not None else BENCH_PATH
        data = yaml.safe_load(path.read_text())
        names = [f.name for f in dataclasses.fields(cls)]
        if not isinstance(data, dict):
            raise ValueError(f"{path}: top level must be a mapping")
        for key in data:
            if key not in names:
                raise ValueError(f"{path}: {key}: unknown key")
        for key in names:
            if key not in data:
                raise ValueError(f"{path}: {key}: missing key")
        vals = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        for key in ("turn_radius", "lookahead", "ref_hold_steps", "start_speed"):
            if len(vals[key]) != 2 or vals[key][0] > vals[key][1]:
                raise ValueError(f"{path}: {key}: must be [low, high] with low <= high")
        for key in ("episodes", "steps", "batch_steps", "batch_repeats"):
            if not isinstance(vals[key], int) or vals[key] < 1:
                raise ValueError(f"{path}: {key}: must be an integer >= 1")
        for kind in vals["route_kinds"]:
            if kind not in ("straight", "left", "right"):
                raise ValueError(f"{path}: route_kinds: unknown kind {kind!r}")
        return cls(**vals)


# ---------------------------------------------------------------------------- problems
def make_route(kind: str, radius: float, bc: BenchConfig) -> np.ndarray:
    """(M, 3) waypoints [x, y, psi] of an approach, a crossing or quarter turn, and an exit."""
    ds = bc.waypoint_spacing
    pts = []
    for s in np.arange(0.0, bc.approach_length, ds):
        pts.append((s, 0.0, 0.0))
    x0 = bc.approach_length
    if kind == "straight":
        length = 2 * radius + bc.exit_length
        for s in np.arange(0.0, length, ds):
            pts.append((x0 + s, 0.0, 0.0))
    else:
        sign = 1.0 if kind == "left" else -1.0
        cy = sign * radius
        for s in np.arange(0.0, radius * math.pi / 2, ds):
            th = s / radius
            pts.append((x0 + radius * math.sin(th), cy - sign * radius * math.cos(th), sign * th))
        ex, ey = x0 + radius, cy
        for s in np.arange(0.0, bc.exit_length, ds):
            pts.append((ex, ey + sign * s, sign * math.pi / 2))
    return np.array(pts)


@dataclass
class Episode:
    X0: np.ndarray       # (T, 4)
    Xref: np.ndarray     # (T, 4)
    Uprev: np.ndarray    # (T, 2)


def generate_problems(cfg: MPCConfig, bc: BenchConfig, episodes: int, progress=None) -> List[Episode]:
    rng = np.random.default_rng(bc.seed)
    ctrl = make_controller(cfg, "fast")
    P = pack_params(cfg)
    out = []
    for _ in range(episodes):
        kind = bc.route_kinds[rng.integers(len(bc.route_kinds))]
        route = make_route(kind, rng.uniform(*bc.turn_radius), bc)
        i0 = rng.integers(0, len(route) // 4)
        rx, ry, rpsi = route[i0]
        off = rng.uniform(-bc.start_lateral_offset, bc.start_lateral_offset)
        x = np.array([rx - off * math.sin(rpsi), ry + off * math.cos(rpsi), rng.uniform(*bc.start_speed),
                      rpsi + rng.uniform(-bc.start_heading_error, bc.start_heading_error)])
        u_prev = np.zeros(2)
        ctrl.reset()
        rows = ([], [], [])
        hold = 0
        ref = None
        for _t in range(bc.steps):
            if hold == 0:
                near = int(np.argmin(np.hypot(route[:, 0] - x[0], route[:, 1] - x[1])))
                ahead = int(round(rng.uniform(*bc.lookahead) / bc.waypoint_spacing))
                wx, wy, wpsi = route[min(near + ahead, len(route) - 1)]
                ref = np.array([wx, wy, bc.ref_speeds[rng.integers(len(bc.ref_speeds))], wpsi])
                hold = int(rng.integers(bc.ref_hold_steps[0], bc.ref_hold_steps[1] + 1))
            hold -= 1
            rows[0].append(x.copy())
            rows[1].append(ref.copy())
            rows[2].append(u_prev.copy())
            res = ctrl.solve(x, ref, u_prev)
            Xn = np.empty((2, 4))
            K.rollout(x, res.u.copy(), P, Xn)
            x = Xn[1].copy()
            x[3] = K.wrap_angle(x[3])
            u_prev = res.u.copy()
        out.append(Episode(*(np.array(r) for r in rows)))
        if progress is not None:
            progress.update(1)
    return out


# ---------------------------------------------------------------------------- runs
def solve_all(ctrl, episodes: List[Episode], progress=None):
    times, costs, oks, iters, us, starts = [], [], [], [], [], []
    for ep in episodes:
        ctrl.reset()
        for x0, xr, up in zip(ep.X0, ep.Xref, ep.Uprev):
            t0 = time.perf_counter()
            res = ctrl.solve(x0, xr, up)
            times.append(time.perf_counter() - t0)
            costs.append(res.cost)
            oks.append(res.ok)
            iters.append(res.iterations)
            us.append(res.u)
            starts.append(res.starts)
            if progress is not None:
                progress.update(1)
    return dict(time=np.array(times), cost=np.array(costs), ok=np.array(oks), iters=np.array(iters),
                u=np.array(us), starts=np.array(starts))


def batch_throughput(cfg: MPCConfig, episodes: List[Episode], B: int, steps: int, threads: int = 1) -> float:
    """Problems per second of solve_batch with B slots (one episode each) on ``threads`` threads."""
    ctrl = make_controller(cfg, "fast")
    ctrl.set_threads(threads)
    T = min(len(ep.X0) for ep in episodes)
    steps = min(steps, T)
    slots = [episodes[i % len(episodes)] for i in range(B)]
    X0 = np.stack([[ep.X0[t] for ep in slots] for t in range(steps)])
    Xr = np.stack([[ep.Xref[t] for ep in slots] for t in range(steps)])
    Up = np.stack([[ep.Uprev[t] for ep in slots] for t in range(steps)])
    ctrl.solve_batch(X0[0], Xr[0], Up[0])   # excluded: allocation of the B warm-start slots, thread start
    ctrl.reset()
    t0 = time.perf_counter()
    for t in range(steps):
        ctrl.solve_batch(X0[t], Xr[t], Up[t])
    return B * steps / (time.perf_counter() - t0)


def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _pct(a, q):
    return float(np.percentile(a, q)) if len(a) else float("nan")


def throughput_row(B: int, threads: tuple, thr: dict, reps: int) -> tuple:
    """The table row of batch size B: median problems/s per thread count, and the median (with
    the range) of the per-pair ratios all threads / one thread."""
    label = " / ".join(str(nt) for nt in threads)
    cells = " / ".join(f"{np.median(thr[B, nt]):,.0f}" for nt in threads)
    if reps > 1:
        cells += " (median of " + str(reps) + ")"
    ratio = ""
    if len(threads) > 1:
        r = np.asarray(thr[B, threads[-1]]) / np.asarray(thr[B, 1])
        ratio = f"{np.median(r):.2f}x" + (f" ({r.min():.2f}-{r.max():.2f})" if reps > 1 else "")
    return (f"solve_batch throughput B={B}, {label} thread(s) [problems/s]", cells, "", ratio)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bimacppo-mpc-bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=None, help="MPC config YAML (default: packaged mpc.yaml)")
    ap.add_argument("--bench-config", default=None, help="benchmark YAML (default: packaged bench.yaml)")
    ap.add_argument("--episodes", type=int, default=None, help="override the number of episodes")
    ap.add_argument("--repeats", type=int, default=None,
                    help="override batch_repeats, the throughput pairs per batch size")
    ap.add_argument("--out", default=None, help="write the results as a markdown table to this file")
    args = ap.parse_args(argv)
    from tqdm import tqdm

    cfg = MPCConfig.load(args.config)
    bc = BenchConfig.load(args.bench_config)
    n_ep = args.episodes if args.episodes is not None else bc.episodes
    if n_ep < 1:
        ap.error("--episodes must be >= 1")
    if args.repeats is not None:
        if args.repeats < 1:
            ap.error("--repeats must be >= 1")
        bc = dataclasses.replace(bc, batch_repeats=args.repeats)

    t0 = time.perf_counter()
    fast = make_controller(cfg, "fast")
    fast.solve([0, 0, 1, 0], [5, 0, 2, 0], [0, 0])          # numba load/compile, not timed
    t_load = time.perf_counter() - t0
    with tqdm(total=n_ep, desc="closed-loop episodes", unit="ep") as bar:
        episodes = generate_problems(cfg, bc, n_ep, bar)
    n = sum(len(e.X0) for e in episodes)
    ipopt = make_controller(cfg, "ipopt")
    ipopt.solve([0, 0, 1, 0], [5, 0, 2, 0], [0, 0])
    rss0 = _peak_rss_mb()
    with tqdm(total=n, desc="fast", unit="pb") as bar:
        rf = solve_all(fast, episodes, bar)
    rss_f = _peak_rss_mb()
    with tqdm(total=n, desc="ipopt", unit="pb") as bar:
        ri = solve_all(ipopt, episodes, bar)
    rss_i = _peak_rss_mb()
    import numba

    threads = (1, numba.config.NUMBA_NUM_THREADS) if numba.config.NUMBA_NUM_THREADS > 1 else (1,)
    reps = bc.batch_repeats
    with tqdm(total=len(bc.batch_sizes) * len(threads) * reps, desc="batched", unit="run") as bar:
        thr = {}
        for B in bc.batch_sizes:
            for nt in threads:
                thr[B, nt] = []
            for _ in range(reps):
                # back to back, so that a pair shares the machine's state and its ratio is fair
                for nt in threads:
                    thr[B, nt].append(batch_throughput(cfg, episodes, B, bc.batch_steps, nt))
                    bar.update(1)

    both = rf["ok"] & ri["ok"]
    gap = (rf["cost"][both] - ri["cost"][both]) / np.maximum(ri["cost"][both], 1e-12)
    du = np.abs(rf["u"][both] - ri["u"][both]).max(axis=1)
    tf, ti = rf["time"], ri["time"]
    med_f, med_i = _pct(tf, 50), _pct(ti, 50)
    p99_f, p99_i = _pct(tf, 99), _pct(ti, 99)
    worse = int((gap > 0.01).sum())
    rows = [
        ("problems (closed-loop steps)", f"{n} from {n_ep} episodes", "", ""),
        ("median solve time", f"{med_f * 1e3:.3f} ms", f"{med_i * 1e3:.3f} ms", f"{med_i / med_f:.1f}x"),
        ("p99 solve time", f"{p99_f * 1e3:.3f} ms", f"{p99_i * 1e3:.3f} ms", f"{p99_i / p99_f:.1f}x"),
        ("max solve time", f"{tf.max() * 1e3:.3f} ms", f"{ti.max() * 1e3:.3f} ms", f"{ti.max() / tf.max():.1f}x"),
        ("iterations median / p99 / max", f"{_pct(rf['iters'], 50):.0f} / {_pct(rf['iters'], 99):.0f} / "
         f"{rf['iters'].max()}", f"{_pct(ri['iters'], 50):.0f} / {_pct(ri['iters'], 99):.0f} / "
         f"{ri['iters'].max()}", ""),
        ("second SQP start run (share of solves)", f"{100.0 * np.mean(rf['starts'] == 2):.1f} %", "", ""),
        ("failures (ok=False)", f"{int((~rf['ok']).sum())}", f"{int((~ri['ok']).sum())}", ""),
        ("process peak RSS after the pass (growth)", f"{rss_f:.0f} MB (+{rss_f - rss0:.0f})",
         f"{rss_i:.0f} MB (+{rss_i - rss_f:.0f})", ""),
        ("cost gap (J_fast - J_ipopt) / J_ipopt, median", f"{_pct(gap, 50):+.2e}", "", ""),
        ("cost gap p99 / max", f"{_pct(gap, 99):+.2e} / {gap.max():+.2e}", "", ""),
        ("cost gap min (fast better)", f"{gap.min():+.2e}", "", ""),
        ("problems with gap > +1% (fast worse) / < -1% (fast better)",
         f"{worse} / {int((gap < -0.01).sum())} of {both.sum()}", "", ""),
        ("share within 1 % of IPOPT or cheaper", f"{100.0 * (1.0 - worse / max(both.sum(), 1)):.1f} %", "", ""),
        ("max |u_fast - u_ipopt| median / p99", f"{_pct(du, 50):.2e} / {_pct(du, 99):.2e}", "", ""),
    ]
    for B in bc.batch_sizes:
        rows.append(throughput_row(B, threads, thr, reps))
    rows.append(("numba load (or compile) on first use", f"{t_load:.1f} s", "", ""))
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    w2 = max(len(r[2]) for r in rows)
    print(f"\n{'':{w0}}  {'fast':{w1}}  {'ipopt':{w2}}  ratio")
    for r in rows:
        print(f"{r[0]:{w0}}  {r[1]:{w1}}  {r[2]:{w2}}  {r[3]}")
    if args.out:
        lines = ["| metric | fast | ipopt | ratio |", "|---|---|---|---|"] + [f"| {a} | {b} | {c} | {d} |"
                                                                     for a, b, c, d in rows]
        lines.append("")
        lines.append(f"Machine: {platform.processor() or platform.machine()}, Python {sys.version.split()[0]}, "
                     f"N = {cfg.horizon}, dt = {cfg.dt} s.")
        pathlib.Path(args.out).write_text("\n".join(lines) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
