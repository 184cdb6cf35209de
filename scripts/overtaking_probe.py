"""A scripted, privileged overtaking driver in the planner's own action space: how much of the
overtaking protocol the road, the SVs and the NMPC allow, whatever a policy learns.

It is a yardstick, not the method, in the way the scripted "yield" driver is for the
intersections: it reads the SVs' true lanes and speeds, which no policy observes. Each decision
it keeps the lane the decisions chose (`action.lane_change_from: chosen`, so one A3 ≠ keep
commits a change), moves one lane towards the nearest lane with no slow SV within 60 m ahead
when the lane it would move into has no SV within 12 m behind or 15 m ahead, and picks the
speed that lets it stop behind the nearest SV ahead in its lane or in the lane it moves to.
With nothing to follow it aims at the farthest waypoint; behind an SV at the farthest waypoint
no more than A2's speed covers in 1 s plus 1.5 m ahead, because the NMPC weighs the reference's
position against its speed and a far waypoint pulls the EV to about 10 m/s whatever A2 says.
``--reach-time T`` instead leaves A1 at the farthest waypoint and lets the decoding bound it
(`action.reach_time`, variant 18). Outcomes are split by how far the free lane lies
(scripts/overtaking_lanes.py).

``--policy P --probe-heads lane`` (or ``speed``) runs a policy with the probe deciding one part of
each action: A3 (``lane``: when and where to change lanes) or A1 and A2 (``speed``: where to aim
and how fast), the policy the rest. It says which part of the task a fine-tune has not learned.
The policy must decode lane changes from the chosen lane (`lane_change_from: chosen`), as the
probe does.

    python scripts/overtaking_probe.py --seed-set validation --episodes 100
    python scripts/overtaking_probe.py --seed-set validation --reach-time 1.5
    python scripts/overtaking_probe.py --policy runs/overtake/policy.pt --probe-heads lane
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from bimacppo_learning.env import IntersectionEnv
from bimacppo_learning.evaluate import SEED_SETS
from bimacppo_planner.decision import EnvConfig
from bimacppo_planner.policy import ACTION_SELECTIONS
from bimacppo_sim.drivers import blocked_lanes

sys.path.insert(0, str(Path(__file__).resolve().parent))
from overtaking_lanes import (MAP, by_distance_markdown, check_records_path, policy_driver,  # noqa: E402
                              run_by_distance, write_records)

CONFIG = Path(__file__).resolve().parents[1] / "studies/config/env_wait_chord_junction_road_overtake_chosen.yaml"
SLOW_SPEED = 5.0        # m/s: an SV ahead slower than this blocks its lane
BLOCK_AHEAD = 60.0      # m: how far ahead a slow SV blocks
GAP_BEHIND, GAP_AHEAD = 12.0, 15.0   # m: the lane moved into is clear of SVs within these
STOP_DECEL = 3.0        # m/s^2: the speed is one that stops behind the SV ahead at this braking
STANDSTILL = 3.0        # m: the gap kept to the SV ahead at a stop
FOLLOW_TIME, FOLLOW_SLACK = 1.0, 1.5   # s, m: behind an SV, aim at most this far ahead (speed * time + slack)


def act(env) -> np.ndarray:
    """The probe's action for the env's current state (reads the world: privileged)."""
    w, road = env.world, env.road
    x, y, v, psi = w.ego_tuple()
    here = road.lane_index(x, y)[1]
    chosen = int(w.start_lane.split("_")[-1]) + env.tracker.lane
    ahead: dict = {lane: [] for lane in range(road.n_lanes)}
    for sv in w.svs:
        if sv.active:
            ahead[road.lane_index(sv.x, sv.y)[1]].append((sv.y - y, sv.v))   # the road runs north

    blocked = blocked_lanes(w, SLOW_SPEED, BLOCK_AHEAD)

    def clear(lane):
        return all(not (-GAP_BEHIND < d < GAP_AHEAD) for d, _ in ahead[lane])
    side = 0
    free = [lane for lane in ahead if lane not in blocked]
    if chosen in blocked and free:
        goal = min(free, key=lambda lane: abs(lane - chosen))
        step = 1 if goal > chosen else -1
        if clear(chosen + step):
            side = step
    target = max(env.cfg.action.speeds)
    for lane in {here, chosen + side}:
        for d, vs in ahead[lane]:
            if d > 0.0:
                gap = max(d - w.cfg.vehicle.length - STANDSTILL, 0.0)
                target = min(target, math.sqrt(2.0 * STOP_DECEL * gap + vs * vs))
    speeds = np.asarray(env.cfg.action.speeds)
    a2 = int(np.max(np.nonzero(speeds <= target + 1e-9)[0], initial=0))
    a1 = env.cfg.action.n_waypoints - 1
    if target < speeds.max() and env.cfg.action.reach_time is None:
        # following: a waypoint the speed covers in about a second, since a farther one pulls the
        # EV above A2's speed (the NMPC weighs the reference's position against its speed)
        a1 = env.tracker.reach_limited(a1, x, y, speeds[a2] * FOLLOW_TIME + FOLLOW_SLACK)
    return np.array([a1, a2, env.cfg.action.lane_change.index(side)])


def run(seed_set: str, episodes: int, slow_max: int = 2, reach_time: float | None = None,
        episodes_out: list | None = None) -> dict:
    """The probe's outcomes by distance (overtaking_lanes.run_by_distance, which appends its
    per-scenario records to ``episodes_out``), with A1's reach bounded by ``reach_time``
    (``action.reach_time``; None: unbounded, the paper's decoding)."""
    cfg = EnvConfig.load(CONFIG, overrides={"action.reach_time": reach_time})
    return run_by_distance(IntersectionEnv(MAP, config=cfg), lambda env, obs: act(env), seed_set, episodes, slow_max,
                           episodes_out)


PROBE_HEADS = {"lane": (2,), "speed": (0, 1)}   # the action entries the probe decides


def run_with_policy(policy, heads: str, seed_set: str, episodes: int, slow_max: int = 2,
                    action: str | None = None, env_config=None) -> dict:
    """Outcomes by distance of ``policy`` (a file, as ``bimacppo-evaluate`` takes it, or an
    object with act/predict, run in ``env_config``) with the probe deciding the action entries of
    ``heads`` (a key of PROBE_HEADS), in the env and with the NMPC the policy records. ValueError
    when the policy does not decode lane changes from the chosen lane."""
    env, policy_act = policy_driver(policy, action, env_config=env_config)
    if env.cfg.action.lane_change_from != "chosen":
        env.close()
        what = policy if isinstance(policy, (str, Path)) else type(policy).__name__
        raise ValueError(f"{what}: decodes lane changes from the {env.cfg.action.lane_change_from!r} lane; "
                         "the probe keeps the chosen one (action.lane_change_from: chosen)")
    idx = list(PROBE_HEADS[heads])

    def mixed(env, obs):
        a = np.array(policy_act(env, obs))
        a[idx] = act(env)[idx]
        return a
    try:
        return run_by_distance(env, mixed, seed_set, episodes, slow_max)
    finally:
        env.close()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seed-set", choices=sorted(SEED_SETS), default="validation")
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--reach-time", type=float, default=None,
                   help="decode with action.reach_time = this (s) and aim at the farthest waypoint (default: off)")
    p.add_argument("--policy", default=None, help="run this policy with the probe deciding --probe-heads")
    p.add_argument("--probe-heads", choices=sorted(PROBE_HEADS), default=None,
                   help="with --policy: the part of each action the probe decides (lane: A3; speed: A1 and A2)")
    p.add_argument("--action", choices=ACTION_SELECTIONS, default=None,
                   help="with --policy: how it picks each head's action (default: the way its file records)")
    p.add_argument("--records", type=Path, default=None,
                   help="the probe alone: also write one JSON line per scenario to this new file "
                        "(as scripts/overtaking_lanes.py --records)")
    args = p.parse_args(argv)
    check_records_path(p, args.records)
    if args.records is not None and args.policy is not None:
        p.error("--records applies to the probe alone")
    if (args.policy is None) != (args.probe_heads is None):
        p.error("--policy and --probe-heads go together")
    if args.policy is not None and args.reach_time is not None:
        p.error("--reach-time applies to the probe alone; a policy decodes as its file records")
    if not 1 <= args.episodes <= 1000:
        p.error(f"--episodes must be in 1..1000, got {args.episodes}")
    if args.reach_time is not None and not (math.isfinite(args.reach_time) and args.reach_time > 0.0):
        p.error(f"--reach-time must be a positive number of seconds, got {args.reach_time}")
    if args.policy is not None:
        try:
            by = run_with_policy(args.policy, args.probe_heads, args.seed_set, args.episodes, action=args.action)
        except (ValueError, OSError) as exc:
            p.error(str(exc))
        part = "A3" if args.probe_heads == "lane" else "A1 and A2"
        print(f"{args.policy} with the probe deciding {part}, {args.seed_set} seeds, {args.episodes} scenarios: "
              "outcomes by distance\n")
        print(by_distance_markdown(by))
        return 0
    records: list = []
    by = run(args.seed_set, args.episodes, reach_time=args.reach_time, episodes_out=records)
    write_records(args.records, records)
    how = "A1 by its speed" if args.reach_time is None else f"action.reach_time {args.reach_time:g} s"
    print(f"scripted overtaking probe ({how}), {args.seed_set} seeds, {args.episodes} scenarios: outcomes by distance\n")
    print(by_distance_markdown(by))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
