"""How far the overtaking scenarios send the EV, and how a policy does at each distance.

For each scenario of the overtaking protocol (`three_lane_straight`, N_sv = 3, up to two slow
SVs: `bimacppo-evaluate --map three_lane_straight --tasks straight --n-sv 3 --slow-svs 2`), the
number of lanes between the EV's start lane and the nearest lane without a slow SV: 0, the EV's
own lane is free (following the SV ahead is enough); 1 or 2, it must change lanes once or twice
to pass. A lane change counted from the route's lane (`action.lane_change_from: route`) reaches
one lane beside the start lane at most, so the scenarios at distance 2 need lane changes counted
from where the EV drives (`ev` or `chosen`, the paper's Fig. 8). Given a policy, the script also
runs it on the same scenarios and splits its outcomes by that distance (off road apart from
collisions with SVs), which says whether it passes slow SVs or only follows free lanes, and
again by whether the EV starts in a lane at the road's edge, with how often A3 asked for a lane
that is not there (a side without an SV is a free lane or no lane at all). Its collisions with SVs
are split by where the SV was at the collision (`collision_kind`): ahead in the EV's lane (a
rear-end collision, with a slow SV or a normal one) or elsewhere (beside or behind: a lane change
into it, or hit from behind), with the EV's speed. Last, per outcome, how many scenarios had a
decision begin with the EV closing on the SV ahead in its lane faster than it could stop behind
it (`bimacppo_sim.drivers.closing_on_lead`, the test the headway price pays on), and for the
collisions how many decisions before the end the first such decision came: whether that price
would reach the decisions that lead to the failures without charging the successes. And per
outcome, how many scenarios had a lane-change reversal: a lane change taken (the decoding's
`lane_change`) within ``REVERSAL_WINDOW`` decisions of one to the other side, before the first
can have been driven (the EV weaving between lanes).

    python scripts/overtaking_lanes.py --seed-set validation --episodes 100
    python scripts/overtaking_lanes.py runs/overtake/policy.pt --seed-set validation --action median
    python scripts/overtaking_lanes.py runs/overtake/policy.pt --env-config studies/config/<variant>.yaml
"""
from __future__ import annotations

import argparse
import json
from collections import Counter

import sys
from pathlib import Path

from bimacppo_common.config import ConfigError
from bimacppo_sim import draw_n_slow
from bimacppo_learning.evaluate import SEED_SETS, EvaluationError, eval_seed
from bimacppo_planner.decision import lanes_beside
from bimacppo_planner.policy import ACTION_SELECTIONS, CheckpointError
from bimacppo_sim import Scenario, World, load_map
from bimacppo_sim.config import DriverConfig
from bimacppo_sim.drivers import closing_on_lead

sys.path.insert(0, str(Path(__file__).resolve().parent))
from failure_causes import CAUSES, cause_of  # noqa: E402  (a sibling script: the one split of outcomes)

MAP = "three_lane_straight"
TASK = 1          # "straight": the only task of the straight road, and the protocol's
N_SV = 3


def free_lane_distance(world: World) -> int:
    """Lanes between the EV's start lane and the nearest lane with no slow SV in it."""
    road = world.road
    slow = {road.lane_index(sv.x, sv.y)[1] for sv in world.svs if sv.slow}
    x, y, _, _ = world.ego_tuple()
    start = road.lane_index(x, y)[1]
    return min(abs(lane - start) for lane in range(road.n_lanes) if lane not in slow)


def distances(seed_set: str, episodes: int, slow_max: int = 2) -> Counter:
    world = World(load_map(MAP))
    out: Counter = Counter()
    for k in range(episodes):
        seed = eval_seed(TASK, N_SV, k, seed_set)
        world.reset(Scenario(n_sv=N_SV, task="straight", seed=seed, n_slow=draw_n_slow(seed, N_SV, slow_max)))
        out[free_lane_distance(world)] += 1
    return out


def at_edge(world: World) -> bool:
    """Whether the EV starts in a lane at the road's edge (one side has no lane)."""
    x, y, _, psi = world.ego_tuple()
    return 0 in lanes_beside(world.road, x, y, psi)


KINDS = ("rear-end, slow SV", "rear-end, normal SV", "beside or behind")
#: decisions within which a lane change to the other side reverses the last one: 2.1 s at the
#: 0.3 s decisions, about the time the NMPC takes to drive one lane change
REVERSAL_WINDOW = 7


def collision_kind(world: World, sv_id: str) -> str:
    """Where the SV the EV collided with was, in the EV's frame at the collision: ahead of the
    EV's centre within half a lane width of its heading line ("rear-end", split by whether the SV
    is one of the scenario's slow ones), or anywhere else."""
    import math
    sv = next(s for s in world.svs if s.id == sv_id)
    x, y, _, psi = world.ego_tuple()
    dx = (sv.x - x) * math.cos(psi) + (sv.y - y) * math.sin(psi)
    dy = -(sv.x - x) * math.sin(psi) + (sv.y - y) * math.cos(psi)
    if dx > 0.0 and abs(dy) < 0.5 * world.road.lane_width:
        return KINDS[0] if sv.slow else KINDS[1]
    return KINDS[2]


def run_by_distance(env, act, seed_set: str, episodes: int, slow_max: int = 2, episodes_out: list | None = None) -> dict:
    """{distance: Counter of failure_causes.CAUSES} of the driver ``act(env, obs) -> action`` on the
    protocol's scenarios, run in ``env`` (an IntersectionEnv on the overtaking map). With
    ``episodes_out`` one record per scenario is appended to it: distance, whether the EV starts at
    the road's edge (``at_edge``), outcome, how many decisions asked A3 for a lane that is not
    there (the side ``lanes_beside`` counts none on, on the map the decoding walks) and, for a
    collision with an SV, its ``collision_kind`` and the EV's speed then; ``closing``, how many
    decisions began with ``closing_on_lead`` true (the headway price's test, drivers.yaml's
    braking), and ``first_closing_before_end``, how many decisions before the end the first of
    them came (None without one); ``reversals``, how many lane changes were taken to the other side
    within ``REVERSAL_WINDOW`` decisions of the previous one."""
    out: dict = {}
    sides = env.cfg.action.lane_change
    drivers = DriverConfig.load()
    for k in range(episodes):
        seed = eval_seed(TASK, N_SV, k, seed_set)
        obs, _ = env.reset(options={"n_sv": N_SV, "task": TASK, "scenario_seed": seed,
                                    "n_slow": draw_n_slow(seed, N_SV, slow_max)})
        d, edge, missing = free_lane_distance(env.world), at_edge(env.world), 0
        closing, first = 0, None        # decisions that began closing on the lead too fast; the first
        last_change, reversals = None, 0     # (decision, side) of the last lane change taken
        t, done = 0, False
        while not done:
            if closing_on_lead(env.world, drivers):
                closing += 1
                first = t if first is None else first
            t += 1
            a = act(env, obs)
            side = sides[int(a[2])]
            if side != 0:
                x, y, _, psi = env.world.ego_tuple()
                missing += lanes_beside(env.world.road, x, y, psi)[0 if side < 0 else 1] == 0
            obs, _, term, trunc, info = env.step(a)
            done = term or trunc
            if info["lane_change"]:
                if last_change is not None and last_change[1] != side and t - last_change[0] <= REVERSAL_WINDOW:
                    reversals += 1
                last_change = (t, side)
        cause = cause_of(info)
        out.setdefault(d, Counter())[cause] += 1
        if episodes_out is not None:
            rec = {"scenario_seed": seed, "distance": d, "edge": edge, "outcome": cause, "a3_no_lane": missing,
                   "closing": closing, "first_closing_before_end": None if first is None else t - first,
                   "reversals": reversals}
            if cause == "sv collision":
                rec["kind"] = collision_kind(env.world, info["collided_with"])
                rec["ev_speed"] = float(env.world.ego_tuple()[2])
            episodes_out.append(rec)
    return out


def policy_driver(policy, action: str | None = None, mpc_config=None, env_config=None):
    """(env, act) for ``policy`` (a file, as ``bimacppo-evaluate`` takes it, or an object with
    act/predict, run in ``env_config``): an IntersectionEnv on the overtaking map with the policy's
    env config and the controller its file records unless ``mpc_config`` says, and its driver
    ``act(env, obs) -> action`` for ``run_by_distance``. The caller closes the env."""
    from bimacppo_learning.env import IntersectionEnv
    from bimacppo_learning.evaluate import (as_actor, check_action, default_selection, resolve_mpc_config,
                                            resolve_policy)
    from bimacppo_planner.policy import with_selection

    spec, loaded, cfg = resolve_policy(policy, env_config)
    actor = as_actor(with_selection(loaded, action or default_selection(spec, loaded), 0))
    env = IntersectionEnv(map_id=MAP, config=cfg, mpc_config=resolve_mpc_config(loaded, mpc_config))
    nvec = tuple(int(n) for n in env.cfg.nvec)
    return env, lambda env, obs: check_action(actor(obs), nvec)


def outcomes_by_distance(policy, seed_set: str, episodes: int, slow_max: int = 2, action: str | None = None,
                         mpc_config=None, episodes_out: list | None = None, env_config=None) -> dict:
    """``run_by_distance`` for ``policy`` (``policy_driver``)."""
    env, act = policy_driver(policy, action, mpc_config, env_config)
    try:
        return run_by_distance(env, act, seed_set, episodes, slow_max, episodes_out)
    finally:
        env.close()


def check_records_path(parser, path) -> None:
    """A usage error for a ``--records`` file that exists (never overwritten) or whose folder does not."""
    if path is None:
        return
    if path.exists():
        parser.error(f"--records {path}: exists; choose another file")
    if not path.parent.is_dir():
        parser.error(f"--records {path}: no folder {path.parent}")


def write_records(path, records: list) -> None:
    """One JSON line per scenario record to ``path`` (nothing when None)."""
    if path is not None:
        path.write_text("".join(json.dumps(r) + "\n" for r in records))


def by_start_lane_markdown(records: list) -> str:
    """Success and A3's asks for a missing lane by distance and start lane (edge or middle)."""
    lines = ["| distance | start lane | scenarios | success | A3 towards no lane (decisions per scenario) |",
             "|---|---|---|---|---|"]
    for d in sorted({r["distance"] for r in records}):
        for edge in (True, False):
            sel = [r for r in records if r["distance"] == d and r["edge"] == edge]
            if sel:
                lines.append(f"| {d} | {'edge' if edge else 'middle'} | {len(sel)} | "
                             f"{sum(r['outcome'] == 'success' for r in sel)} | "
                             f"{sum(r['a3_no_lane'] for r in sel) / len(sel):.1f} |")
    return "\n".join(lines)


def collisions_markdown(records: list) -> str:
    """The collisions with SVs by distance and ``collision_kind``: count, and the EV's speed range."""
    lines = ["| distance | " + " | ".join(KINDS) + " |", "|---|" + "---|" * len(KINDS)]
    for d in sorted({r["distance"] for r in records}):
        cells = []
        for kind in KINDS:
            v = [r["ev_speed"] for r in records if r["distance"] == d and r.get("kind") == kind]
            cells.append(f"{len(v)} ({min(v):.1f}-{max(v):.1f} m/s)" if v else "0")
        lines.append(f"| {d} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def closing_markdown(records: list) -> str:
    """Per outcome: scenarios, those with a decision that began closing on the lead too fast to
    stop (``closing_on_lead``), and how many decisions before the end the first of them came."""
    lines = ["| outcome | scenarios | with a closing decision | first one, decisions before the end |",
             "|---|---|---|---|"]
    for cause in CAUSES:
        sel = [r for r in records if r["outcome"] == cause]
        if not sel:
            continue
        lead = [r["first_closing_before_end"] for r in sel if r["closing"]]
        span = f"{min(lead)}-{max(lead)}" if lead else "-"
        lines.append(f"| {cause} | {len(sel)} | {len(lead)} | {span} |")
    return "\n".join(lines)


def reversals_markdown(records: list) -> str:
    """Per outcome: scenarios, and those with a lane-change reversal (``reversals``) and how many."""
    lines = [f"| outcome | scenarios | with a reversal (a change to the other side within {REVERSAL_WINDOW} "
             "decisions) | reversals |", "|---|---|---|---|"]
    for cause in CAUSES:
        sel = [r for r in records if r["outcome"] == cause]
        if sel:
            lines.append(f"| {cause} | {len(sel)} | {sum(r['reversals'] > 0 for r in sel)} | "
                         f"{sum(r['reversals'] for r in sel)} |")
    return "\n".join(lines)


def by_distance_markdown(by: dict) -> str:
    """The outcome table of ``run_by_distance``, one row per distance and a total."""
    lines = ["| distance | scenarios | " + " | ".join(CAUSES) + " |", "|---|---|" + "---|" * len(CAUSES)]
    for d in sorted(by):
        lines.append(f"| {d} | {sum(by[d].values())} | " + " | ".join(str(by[d][o]) for o in CAUSES) + " |")
    total = sum(by.values(), Counter())
    lines.append(f"| all | {sum(total.values())} | " + " | ".join(str(total[o]) for o in CAUSES) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("policy", nargs="?", default=None,
                   help="a policy file: also run it and split its outcomes by distance")
    p.add_argument("--seed-set", choices=sorted(SEED_SETS), default="validation")
    p.add_argument("--action", choices=ACTION_SELECTIONS, default=None,
                   help="how the policy picks each head's action (default: the way its file records)")
    p.add_argument("--mpc-config", default=None, help="NMPC config (default: the one the policy records)")
    p.add_argument("--env-config", default=None,
                   help="env config YAML to run the policy in (default: the one it records), e.g. to try a "
                        "decoding variant on a trained policy; the observation and the action heads must match")
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--slow-svs", type=int, default=2, help="at most this many slow SVs per scenario (protocol: 2)")
    p.add_argument("--records", type=Path, default=None,
                   help="with a policy: also write one JSON line per scenario (its scenario_seed, distance, "
                        "outcome, ...) to this new file, e.g. to compare which scenarios two drivers fail")
    args = p.parse_args(argv)
    if not 1 <= args.episodes <= 1000:
        p.error(f"--episodes must be in 1..1000, got {args.episodes}")
    check_records_path(p, args.records)
    if args.records is not None and args.policy is None:
        p.error("--records needs a policy: the distances alone have no per-scenario outcomes")
    if not 0 <= args.slow_svs <= N_SV:
        p.error(f"--slow-svs must be in 0..{N_SV}, got {args.slow_svs}")
    c = distances(args.seed_set, args.episodes, args.slow_svs)
    print(f"{args.seed_set} seeds, {args.episodes} overtaking scenarios: lanes from the EV's start lane to "
          f"the nearest one without a slow SV")
    for d in sorted(c):
        print(f"  {d}: {c[d]} scenarios ({100.0 * c[d] / args.episodes:.0f} %)")
    if args.policy is not None:
        records: list = []
        try:
            by = outcomes_by_distance(args.policy, args.seed_set, args.episodes, args.slow_svs, args.action,
                                      args.mpc_config, records, args.env_config)
        except (ConfigError, EvaluationError, CheckpointError) as exc:
            p.error(str(exc))
        write_records(args.records, records)
        print(f"\n{args.policy}, {args.action or 'recorded'} actions: outcomes by distance\n")
        print(by_distance_markdown(by))
        print("\nby start lane (edge: a lane with no lane beside it on one side)\n")
        print(by_start_lane_markdown(records))
        print("\ncollisions with SVs by where the SV was (EV speed at the collision)\n")
        print(collisions_markdown(records))
        print("\nscenarios with a decision closing on the lead faster than the EV can stop behind it "
              "(the headway price's test)\n")
        print(closing_markdown(records))
        print("\nlane-change reversals (the EV weaving between lanes)\n")
        print(reversals_markdown(records))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
