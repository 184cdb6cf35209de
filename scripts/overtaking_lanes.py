"""How far the overtaking scenarios send the EV: for each scenario of the overtaking protocol
(`three_lane_straight`, N_sv = 3, up to two slow SVs, `bimacppo-evaluate --map
three_lane_straight --tasks straight --n-sv 3 --slow-svs 2`), how many lanes lie between the EV's
start lane and the nearest lane without a slow SV. A lane change counted from the route's lane
(`action.lane_change_from: route`) reaches one lane beside the start lane at most, so the
scenarios at distance 2 need lane changes counted from the EV's (`ev`), the paper's Fig. 8.

    python scripts/overtaking_lanes.py --seed-set validation --episodes 100
"""
from __future__ import annotations

import argparse
from collections import Counter

from bimacppo_learning.batch import draw_n_slow
from bimacppo_learning.evaluate import SEED_SETS, eval_seed
from bimacppo_sim import Scenario, World, load_map

MAP = "three_lane_straight"
TASK = 1          # "straight": the only task of the straight road, and the protocol's
N_SV = 3


def free_lane_distance(world: World) -> int:
    """Lanes between the EV's start lane and the nearest lane with no slow SV in it."""
    road = world.road
    slow = {road.lane_index(sv.x, sv.y)[1] for sv in world.svs if sv.slow}
    start = road.lane_index(world._ev[0], world._ev[1])[1]
    return min(abs(lane - start) for lane in range(road.n_lanes) if lane not in slow)


def distances(seed_set: str, episodes: int, slow_max: int = 2) -> Counter:
    world = World(load_map(MAP))
    out: Counter = Counter()
    for k in range(episodes):
        seed = eval_seed(TASK, N_SV, k, seed_set)
        world.reset(Scenario(n_sv=N_SV, task="straight", seed=seed, n_slow=draw_n_slow(seed, N_SV, slow_max)))
        out[free_lane_distance(world)] += 1
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed-set", choices=sorted(SEED_SETS), default="validation")
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--slow-svs", type=int, default=2, help="at most this many slow SVs per scenario (protocol: 2)")
    args = p.parse_args(argv)
    if not 1 <= args.episodes <= 1000:
        p.error(f"--episodes must be in 1..1000, got {args.episodes}")
    if not 0 <= args.slow_svs <= N_SV:
        p.error(f"--slow-svs must be in 0..{N_SV}, got {args.slow_svs}")
    c = distances(args.seed_set, args.episodes, args.slow_svs)
    print(f"{args.seed_set} seeds, {args.episodes} overtaking scenarios: lanes from the EV's start lane to "
          f"the nearest one without a slow SV")
    for d in sorted(c):
        print(f"  {d}: {c[d]} scenarios ({100.0 * c[d] / args.episodes:.0f} %)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
