"""Micro-benchmark: cost of sample() + update() per episode for every scheduler.

Prints figures; asserts nothing (timings on a shared machine are noisy). The curriculum
runs once per *episode*, so anything under a millisecond is invisible next to an episode
of simulation + MPC; the point is to catch an accidental O(history) or O(t) cost.

    python -m bimacppo_curriculum.bench [--episodes 20000] [--repeats 3]
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from . import SCHEDULERS, make_scheduler


def bench(name: str, episodes: int, repeats: int) -> dict:
    rng = np.random.default_rng(0)
    rets = rng.normal(0.0, 20.0, episodes)
    best = {}
    for _ in range(repeats):
        s = make_scheduler(name, seed=0, total_episodes=episodes, config={"sync_interval": 100} if name in ("bimab", "rd") else None)
        t0 = time.perf_counter()
        for k in range(episodes):
            i, j = s.sample()
            s.update(i, j, float(rets[k]))
        t1 = time.perf_counter()
        for _ in range(1000):
            s.log_dict()
        t2 = time.perf_counter()
        state = s.state_dict()
        t3 = time.perf_counter()
        for _ in range(100):
            make_scheduler(name, seed=0, total_episodes=episodes, config=s.config).load_state_dict(json.loads(json.dumps(state)))
        t4 = time.perf_counter()
        cur = {"sample+update_us": (t1 - t0) / episodes * 1e6, "log_dict_us": (t2 - t1) / 1000 * 1e6,
               "state_roundtrip_ms": (t4 - t3) / 100 * 1e3}
        best = {k: min(v, best.get(k, float("inf"))) for k, v in cur.items()}
    return best


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    print(f"best of {args.repeats}, {args.episodes} episodes each (sync_interval 100 for bandits)\n")
    print("| scheduler | sample+update (µs/episode) | log_dict (µs) | state_dict JSON round trip + load (ms) |")
    print("|---|---:|---:|---:|")
    for name in SCHEDULERS:
        b = bench(name, args.episodes, args.repeats)
        print(f"| {name} | {b['sample+update_us']:.1f} | {b['log_dict_us']:.1f} | {b['state_roundtrip_ms']:.2f} |")


if __name__ == "__main__":
    main()
