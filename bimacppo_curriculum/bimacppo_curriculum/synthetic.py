"""A synthetic learner to exercise the curricula without the simulator or PPO.

The learner has a competence c_ij in [0, 1] per scenario Omega_ij (= its success
probability there). Practising Omega_ij raises c toward 1; the gain is slower for harder
scenarios (more SVs, left > straight > right) and is gated by the competence on the same
task with one SV fewer ("rewards of harder arms rise after easier ones saturate"). Practice
also spills over to the other tasks of the cluster and, more weakly, to other clusters,
as a shared policy would. Returns follow the shape of the paper's eq. (26)-(28): a success
pays base + alpha1*N_sv + alpha2*N_pcp, a collision costs alpha4*N_sv*v, a timeout a constant.

It is a check of the *mechanism* (does the bandit move its weight the way §IV-B describes
when the returns behave like that?), not a claim about driving.

CLI: ``python -m bimacppo_curriculum.synthetic --out docs/img`` (see docs/results_curriculum.md).
"""
from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from . import SCHEDULERS, make_scheduler
from .config import SyntheticConfig


class SyntheticLearner:
    def __init__(self, config=None, seed: int = 0):
        self.config = SyntheticConfig.resolve(config)
        c = self.config
        self.rng = np.random.default_rng([seed, 0x5EED])   # independent of the scheduler's stream
        k = c.n_sv_max + 1
        self.competence = np.full((k, 3), c.initial_competence)
        sv = np.arange(k)[:, None]
        self.difficulty = c.difficulty_per_sv * sv + np.asarray(c.task_difficulty)[None, :]
        self.n_pcp = sv * np.asarray(c.pcp_per_sv)[None, :]

    def success_return(self, i: int, j: int) -> float:
        c = self.config
        return c.success_base + c.success_per_sv * i + c.success_per_pcp * self.n_pcp[i, j]

    def episode(self, i: int, j: int) -> tuple[float, bool]:
        """Play Omega_ij once with the current competence: (return, success)."""
        c = self.config
        u_success, u_kind, u_speed = self.rng.random(3)
        noise = c.return_noise * self.rng.standard_normal()
        success = u_success < self.competence[i, j]
        if success:
            r = self.success_return(i, j)
        elif i > 0 and u_kind < c.collision_share:
            v = c.collision_speed_min + (c.collision_speed_max - c.collision_speed_min) * u_speed
            r = -c.collision_per_sv_speed * i * v
        else:
            r = c.timeout_return
        return float(r + noise), bool(success)

    def practice(self, i: int, j: int) -> None:
        """One episode of training on Omega_ij."""
        c = self.config
        k = self.competence.shape[0]
        dist = np.abs(np.arange(k) - i)[:, None]
        transfer = np.where(dist == 0, c.transfer_same_cluster, c.transfer_other_cluster ** dist) * np.ones((1, 3))
        transfer[i, j] = 1.0
        ready = np.ones_like(self.competence)
        ready[1:] = np.clip(self.competence[:-1] / c.mastery, c.readiness_floor, 1.0)
        rate = c.learn_rate / (1.0 + self.difficulty)
        self.competence += rate * transfer * ready * (1.0 - self.competence)


def run(scheduler, learner: SyntheticLearner, episodes: int, log_every: int = 50) -> list[dict]:
    """Train the synthetic learner under `scheduler`; return log_dict snapshots (+ learner metrics)."""
    if episodes < 1 or log_every < 1:
        raise ValueError(f"episodes and log_every must be >= 1, got {episodes}, {log_every}")
    history = []

    def snap():
        rec = scheduler.log_dict()
        rec["mean_competence"] = float(learner.competence.mean())
        rec["min_competence"] = float(learner.competence.min())
        for i in range(learner.competence.shape[0]):
            rec[f"competence_{i}"] = float(learner.competence[i].mean())
        history.append(rec)

    snap()
    for t in range(1, episodes + 1):
        i, j = scheduler.sample()
        r, _ = learner.episode(i, j)
        learner.practice(i, j)
        scheduler.update(i, j, r)
        if t % log_every == 0 or t == episodes:
            snap()
    return history


def run_named(name: str, seed: int, episodes: int, log_every: int = 50, overrides: dict | None = None,
              learner_config=None) -> list[dict]:
    sched = make_scheduler(name, seed=seed, total_episodes=episodes, config=overrides or None)
    return run(sched, SyntheticLearner(learner_config, seed=seed), episodes, log_every)


def _window_shares(history: list[dict], n_clusters: int, lo: float, hi: float) -> np.ndarray:
    """Share of samples per cluster drawn between episode fractions lo and hi of the run."""
    eps = np.array([h["episodes"] for h in history])
    total = eps[-1]
    a = history[int(np.searchsorted(eps, lo * total))]
    b = history[int(np.searchsorted(eps, hi * total))]
    d = np.array([b[f"count_{i}"] - a[f"count_{i}"] for i in range(n_clusters)])
    return d / max(d.sum(), 1.0)


def main(argv=None) -> None:
    from . import plots

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=5000)
    ap.add_argument("--sync-interval", type=int, default=None, help="override N_BiMAB (and RD's)")
    ap.add_argument("--alpha", type=float, default=None, help="override the step sizes alpha_c, alpha_a (and RD's)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the run that is plotted as Figs. 5-6")
    ap.add_argument("--seeds", type=int, default=5, help="seeds per scheduler for the comparison")
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("docs/img"))
    ap.add_argument("--prefix", default="curriculum_synthetic")
    args = ap.parse_args(argv)

    ov = {"sync_interval": args.sync_interval} if args.sync_interval else {}
    alpha = {"alpha_c": args.alpha} if args.alpha else {}
    overrides = {"bimab": {**ov, **alpha, **({"alpha_a": args.alpha} if args.alpha else {})}, "rd": {**ov, **alpha}}
    hist = run_named("bimab", args.seed, args.episodes, overrides=overrides["bimab"])
    n = sum(1 for k in hist[0] if k.startswith("cluster_prob_"))
    p = args.out / args.prefix
    made = [plots.plot_cluster_weights(hist, f"{p}_fig5_clusters.png",
                                       title=f"BiMAB cluster weights, synthetic learner (seed {args.seed})"),
            plots.plot_arm_weights(hist, f"{p}_fig6_arms.png",
                                   title=f"BiMAB arm weights, synthetic learner (seed {args.seed})"),
            plots.plot_cluster_probabilities(hist, f"{p}_probs.png",
                                             title="BiMAB sampling probability per cluster (synthetic learner)")]
    print(f"## BiMAB on the synthetic learner, seed {args.seed}, {args.episodes} episodes\n")
    print(plots.counts_table_markdown(hist[-1]))
    for lo, hi in ((0.0, 0.25), (0.25, 0.5), (0.5, 0.75), (0.75, 1.0)):
        s = _window_shares(hist, n, lo, hi)
        print(f"\nshare of samples per N_sv, episodes {lo:.0%}-{hi:.0%}: " + ", ".join(f"{x:.2f}" for x in s))

    curves, finals = {}, {}
    for name in SCHEDULERS:
        runs = [run_named(name, s, args.episodes, overrides=overrides.get(name)) for s in range(args.seeds)]
        x = np.array([h["episodes"] for h in runs[0]])
        y = np.array([[h["mean_competence"] for h in r] for r in runs])
        curves[name] = (x, y.mean(0), y.std(0))
        last = np.array([[r[-1][f"competence_{i}"] for i in range(n)] for r in runs])
        at = [y[:, int(np.searchsorted(x, f * x[-1]))] for f in (0.25, 0.5)]
        finals[name] = (at[0], at[1], y[:, -1], last)
    made.append(plots.plot_curves(curves, f"{p}_compare.png", ylabel="mean competence over all 12 scenarios",
                                  title=f"Synthetic learner under each scheduler ({args.seeds} seeds, mean ± std)"))
    print(f"\n## Mean competence of the synthetic learner over the 12 scenarios ({args.seeds} seeds, mean ± std)\n")
    print("| scheduler | at 25% | at 50% | at end | " + " | ".join(f"end, N_sv={i}" for i in range(n)) + " |")
    print("|---|---:|---:|---:|" + "---:|" * n)
    for name, (q1, q2, allc, last) in finals.items():
        print(f"| {name} | " + " | ".join(f"{v.mean():.3f} ± {v.std():.3f}" for v in (q1, q2, allc)) + " | "
              + " | ".join(f"{last[:, i].mean():.3f}" for i in range(n)) + " |")
    print("\nfigures: " + json.dumps([str(m) for m in made]))


if __name__ == "__main__":
    main()
