"""Why a policy's episodes fail, per task: a collision with an SV, leaving the road, or the time
limit. `bimacppo-evaluate` counts collisions; this script splits them, because the two need
different remedies (an SV collision is a decision the policy took, leaving the road is what the
decoded reference asked of the NMPC). For each SV collision it also prints the EV's speed and
whether the EV had entered a threatened junction.

    python scripts/failure_causes.py bimacppo_planner/bimacppo_planner/policies/bimacppo_dual_lane.pt \\
        --seed-set validation --episodes 30 --n-sv 3
"""
from __future__ import annotations

import argparse
from collections import Counter

from bimacppo_common.conventions import TASKS
from bimacppo_learning.env import IntersectionEnv
from bimacppo_learning.evaluate import (SEED_SETS, as_actor, check_action, default_selection, eval_seed, resolve_mpc_config,
                                        resolve_policy)
from bimacppo_planner.policy import ACTION_SELECTIONS, with_selection

CAUSES = ("success", "sv collision", "off road", "timeout")


def cause_of(info: dict) -> str:
    """One of CAUSES for the final ``info`` of an episode."""
    if info["outcome"] != "collision":
        return info["outcome"]
    return "off road" if info["collided_with"] == "offroad" else "sv collision"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("policy", nargs="?", default=None, help="policy file (default: the shipped policy)")
    p.add_argument("--map", default="dual_lane_4way")
    p.add_argument("--tasks", nargs="+", choices=TASKS, default=list(TASKS))
    p.add_argument("--n-sv", type=int, default=3)
    p.add_argument("--episodes", type=int, default=30)
    p.add_argument("--seed-set", choices=sorted(SEED_SETS), default="validation")
    p.add_argument("--action", choices=ACTION_SELECTIONS, default=None,
                   help="how the policy picks each head's action (default: the way the file records)")
    a = p.parse_args(argv)
    spec, loaded, cfg = resolve_policy(a.policy)
    actor = as_actor(with_selection(loaded, a.action or default_selection(spec, loaded), 0))
    env = IntersectionEnv(map_id=a.map, config=cfg, mpc_config=resolve_mpc_config(loaded))
    nvec = tuple(int(n) for n in env.cfg.nvec)
    print(f"{spec[1]}, {a.map}, N_sv = {a.n_sv}, {a.episodes} episodes per task ({a.seed_set} seeds)\n")
    print("| task | " + " | ".join(CAUSES) + " |")
    print("|---|" + "---|" * len(CAUSES))
    details = []
    try:
        for task in a.tasks:
            t = TASKS.index(task)
            counts: Counter = Counter()
            for k in range(a.episodes):
                seed = eval_seed(t, a.n_sv, k, a.seed_set)
                obs, _ = env.reset(options={"n_sv": a.n_sv, "task": t, "scenario_seed": seed})
                done = False
                while not done:
                    obs, _, term, trunc, info = env.step(check_action(actor(obs), nvec))
                    done = term or trunc
                cause = cause_of(info)
                counts[cause] += 1
                if cause == "sv collision":
                    details.append(f"{task} episode {k}: hit {info['collided_with']} at {env.world.ego[2]:.1f} m/s "
                                   f"after {info['sim_time']:.1f} s, threatened entry: {info['threat_entry']}")
            print(f"| {task} | " + " | ".join(str(counts[c]) for c in CAUSES) + " |", flush=True)
    finally:
        env.close()
    if details:
        print("\n" + "\n".join(details))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
