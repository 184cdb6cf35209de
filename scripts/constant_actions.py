"""Success / collision / timeout of every constant (A1 waypoint, A2 speed) action, lane kept, in
one evaluation cell: how much of a cell the action space itself makes easy or impossible,
before any learning. A constant action that always fails shows a region the policy must learn
to avoid; one that always succeeds shows what a policy could at least reach.

    python scripts/constant_actions.py --task right --n-sv 0 --episodes 20 \\
        --env-config bimacppo_learning/bimacppo_learning/config/env_yield_far.yaml
"""
from __future__ import annotations

import argparse

import numpy as np

from bimacppo_common.conventions import TASKS
from bimacppo_learning.evaluate import SEED_SETS, evaluate
from bimacppo_planner.decision import EnvConfig


class Constant:
    def __init__(self, action):
        self.action = np.asarray(action, np.int64)

    def act(self, obs):
        return self.action


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--map", default="dual_lane_4way")
    p.add_argument("--task", choices=TASKS, default="right")
    p.add_argument("--n-sv", type=int, default=0)
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--env-config", default=None, help="variant YAML (default: the packaged env.yaml)")
    p.add_argument("--seed-set", choices=sorted(SEED_SETS), default="validation")
    a = p.parse_args(argv)
    cfg = EnvConfig.load(a.env_config) if a.env_config else EnvConfig.load()
    keep = cfg.action.lane_change.index(0)
    speeds = cfg.action.speeds
    print(f"{a.map}, {a.task}, N_sv = {a.n_sv}, {a.episodes} episodes per action ({a.seed_set} seeds), "
          "S / C / TO counts, lane kept\n")
    print("| A1 \\ A2 | " + " | ".join(f"{v:g} m/s" for v in speeds) + " |")
    print("|---|" + "---|" * len(speeds))
    for a1 in range(cfg.action.n_waypoints):
        row = []
        for a2 in range(len(speeds)):
            c = evaluate(Constant([a1, a2, keep]), map_id=a.map, n_svs=(a.n_sv,), tasks=(TASKS.index(a.task),),
                         episodes=a.episodes, workers=1, random_row=False, env_config=cfg, seed_set=a.seed_set)[0]
            row.append(" / ".join(str(c.counts.get(k, 0)) for k in ("success", "collision", "timeout")))
        print(f"| WP{a1} | " + " | ".join(row) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
