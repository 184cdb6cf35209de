#!/usr/bin/env python3
"""Micro-benchmark of the PPO core: single-observation inference latency and update throughput.

Prints figures; asserts nothing.  Run: .venv/bin/python scripts/bench_ppo.py [--obs-dim 16]
Shared, loaded machines give noisy numbers: look at the median and the spread.
"""
import argparse
import pathlib
import tempfile
import time

import numpy as np
import torch

from bimacppo_learning.checkpoint import Policy, export_policy
from bimacppo_learning.ppo import PPO
from bimacppo_learning.ppo_config import load_config

NVEC = (5, 5, 3)


def timeit(fn, n):
    ts = np.empty(n)
    for k in range(n):
        t0 = time.perf_counter()
        fn()
        ts[k] = time.perf_counter() - t0
    return ts


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--obs-dim", type=int, default=16, help="4 ego + 4 x N_sv^max(3), eq. (18)")
    ap.add_argument("--n-infer", type=int, default=5000)
    ap.add_argument("--updates", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: config)")
    args = ap.parse_args()
    pcfg, tcfg = load_config()
    torch.set_num_threads(args.threads or tcfg.torch_threads)
    agent = PPO(args.obs_dim, NVEC, pcfg, seed=0)
    rng = np.random.default_rng(0)
    agent.normalize_obs(rng.normal(size=(1000, args.obs_dim)), update=True)
    obs = rng.normal(size=args.obs_dim).astype(np.float32)

    with tempfile.TemporaryDirectory() as d:
        path = export_policy(agent, pathlib.Path(d) / "policy.pt")
        size = path.stat().st_size
        pol = Policy.load(path)
    pol.act(obs)
    ts = timeit(lambda: pol.act(obs, deterministic=True), args.n_infer)
    print(f"Policy.act (numpy, 1 obs, deterministic): median {np.median(ts) * 1e6:.1f} us, "
          f"p99 {np.percentile(ts, 99) * 1e6:.1f} us  (policy file {size / 1024:.0f} KiB)")
    ts = timeit(lambda: agent.act(agent.normalize_obs(obs[None]), deterministic=True), args.n_infer // 5)
    print(f"PPO.act  (torch, 1 obs, deterministic):  median {np.median(ts) * 1e6:.1f} us, "
          f"p99 {np.percentile(ts, 99) * 1e6:.1f} us")

    n = tcfg.rollout_steps * tcfg.num_envs
    o = agent.normalize_obs(rng.normal(size=(n, args.obs_dim)))
    a, lp, _ = agent.act(o)
    adv = rng.normal(size=n).astype(np.float32)
    ret = rng.normal(size=n).astype(np.float32)
    rates = []
    for _ in range(args.updates):
        t0 = time.perf_counter()
        st = agent.update(o, a, lp, adv, ret)
        dt = time.perf_counter() - t0
        rates.append(n / dt)
    print(f"PPO.update: rollout {n} samples, minibatch {pcfg.minibatch_size}, {pcfg.epochs} epochs "
          f"({int(st['minibatch_steps'])} minibatch steps): median {np.median(rates):.0f} samples/s "
          f"({n / np.median(rates):.2f} s per update; x{pcfg.epochs} epochs = "
          f"{np.median(rates) * pcfg.epochs:.0f} sample-gradients/s), torch threads {torch.get_num_threads()}")


if __name__ == "__main__":
    main()
