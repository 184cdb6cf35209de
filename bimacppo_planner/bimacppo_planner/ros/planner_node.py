"""Planner node: the trained policy (``HighLevelPlanner``) between the world's state and x_IMR.

For each state stamp s that has both /ego/odom and /objects, it publishes
/planner/reference (x_IMR) stamped s. A new /goal_pose starts an episode
(``hp.reset(ego, goal)``: A* on the planner's own copy of the road map); repeats of a
stamp (the same state again) are answered from a cache, so the policy's internal state (waypoint tracker)
advances once per tick exactly as in the in-process loop. As in ``IntersectionEnv``, a
decision is taken every ``action.decision_every`` ticks of the agent's environment config
and held in between.

When the world reports the end of the episode (/episode/result), the planner republishes
that result on /planner/episode_result with ``return`` added: the return is the agent's
(``decision.step_reward``, eq. 26-28, the function the environment uses), not a fact of
the world, so it is computed here. ``n_pcp`` is the source's key-value when it sends one;
otherwise the planner infers it from its own map (``RoadMap.infer_n_pcp``: the EV's start
lane, the goal's lane, each SV's first and last lane) and adds it to the message.

Frames: the map file's ``pose`` says where its junction sits in the ``map`` frame; states,
SVs and goal are moved into the map's own frame before the policy sees them and x_IMR is
moved back (``geometry.MapFrame``), so a source whose junction is elsewhere needs only the
matching map file (``map_id``: a map id or a YAML path).

``action_selection`` (argmax or median; empty, the default: what the policy file records, else
argmax) is how the policy turns each head's distribution into an action; both are deterministic (``bimacppo_planner.policy.head_median``
says when they differ and why a waiting policy needs the median).

Faults (docs/faults.md): callbacks are ``runtime.guarded``; which input is answered,
repeated, kept or dropped is the tick protocol's verdict (``tick_protocol.TickProtocol``,
its table in docs/interfaces.md: stale and far-future stamps, goals and results far ahead,
a restarted source, a refused tick the source keeps re-sending); a policy step
that raises or returns a non-finite x_IMR is logged and that tick left unanswered (the
controller's watchdog then stops the vehicle).
"""
from __future__ import annotations

import importlib
import inspect
from collections import OrderedDict

import numpy as np
from rclpy.node import Node

from bimacppo_planner.agent import HighLevelPlanner
from bimacppo_planner.decision import EnvConfig, step_reward
from bimacppo_sim.geometry import MapFrame
from bimacppo_interfaces import contract as I
from bimacppo_ros_common.params import ConfigError, declare, param_file
from bimacppo_ros_common.runtime import guarded, one_line, run_single
from bimacppo_ros_common.tick_protocol import MAX_STAMP_JUMP_S, REFUSED, TickProtocol, Verdict

DEFAULT_CLASS = "bimacppo_planner.agent:HighLevelPlanner"


PLANNER_GROUP = "bimacppo.planners"
PLANNER_METHODS = ("load", "reset", "step")


def load_class(spec: str):
    """The planner class ``spec`` names: an entry point of the ``bimacppo.planners`` group
    (``default`` is HighLevelPlanner; other packages add their own), or ``module:Class``.

    Only a class with the planner interface (``load``, ``reset``, ``step``) is accepted, so the
    parameter cannot reach an arbitrary callable (``os:system``) or an unprotected loader
    (``torch.serialization:load``). ValueError names what is wrong."""
    spec = str(spec).strip()
    if ":" not in spec:
        from importlib.metadata import entry_points

        found = [ep for ep in entry_points(group=PLANNER_GROUP) if ep.name == spec]
        if not found:
            names = sorted(ep.name for ep in entry_points(group=PLANNER_GROUP))
            raise ValueError(f"planner_class {spec!r} is neither 'package.module:Class' nor a "
                             f"registered planner (entry points {PLANNER_GROUP}: {names})")
        spec = found[0].value
    mod, _, name = spec.partition(":")
    if not mod or not name:
        raise ValueError(f"planner_class must look like 'package.module:Class', got {spec!r}")
    try:
        obj = getattr(importlib.import_module(mod), name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"planner_class {spec!r} is not importable: {exc}") from None
    missing = [m for m in PLANNER_METHODS if not callable(getattr(obj, m, None))]
    if not inspect.isclass(obj) or missing:
        raise ValueError(f"planner_class {spec!r} is not a planner class (a class with "
                         f"{', '.join(PLANNER_METHODS)}; missing: {missing or 'not a class'})")
    return obj


def make_planner(spec: str, policy_path: str, map_id: str, action_selection: str = ""):
    """``cls.load(policy_path, map_id)``; an empty path means the policy shipped in the package.
    A non-empty ``action_selection`` is passed on (``action_selection=``; empty: the policy's
    own); a class whose ``load`` does not take it is refused for anything but the argmax rather
    than silently run by argmax.

    A missing or unusable policy file becomes a ValueError naming the file, so the node
    exits with one ``error:`` line (runtime.run_single) instead of a traceback.
    """
    cls = load_class(spec)
    from bimacppo_planner.policy import CheckpointError
    if policy_path:
        param_file(policy_path, "policy_path", "planner")
    kw = {}
    if action_selection:
        params = inspect.signature(cls.load).parameters
        if "action_selection" in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            kw["action_selection"] = action_selection
        elif action_selection != "argmax":
            raise ConfigError(f"planner: planner_class {spec!r} does not take action_selection "
                              f"(asked for {action_selection!r})")
    try:
        return cls.load(policy_path or None, map_id, **kw)
    except (CheckpointError, ValueError, KeyError, TypeError, RuntimeError, OSError) as exc:
        # RuntimeError/KeyError/TypeError: torch refusing a state dict of the wrong shape
        # or layout; OSError: unreadable; ValueError: a bad map_id or config
        hint = "" if policy_path else " (no policy_path given: the shipped policy was used)"
        raise ConfigError(f"planner: policy/map not usable: {type(exc).__name__}: {one_line(exc)}{hint}") from None


def episode_return(lane_changes, outcome: str, facts: dict, reward_cfg) -> float:
    """The agent's return of one episode, exactly as ``IntersectionEnv`` sums it.

    ``lane_changes`` holds one flag per decision. Every decision earns
    ``step_reward(cfg, changed)``; the last one also the terminal term of eq. (26)-(28),
    because in the environment the decision whose ticks end the episode gets it.
    ``facts`` are the world's result key-values (n_sv, n_pcp, speed, dist_to_goal), as
    strings or numbers; a missing fact is a KeyError, not a silently wrong return.
    """
    flags = [bool(c) for c in lane_changes]
    if not flags:
        raise ValueError("episode return: the episode has no decision")
    total = sum(step_reward(reward_cfg, c) for c in flags[:-1])
    return float(total + step_reward(reward_cfg, flags[-1], outcome, int(facts["n_sv"]),
                                     int(facts["n_pcp"]), float(facts["speed"]),
                                     float(facts["dist_to_goal"])))


class PlannerNode(Node):
    """Thin adapter over ``HighLevelPlanner.reset/step``."""

    def __init__(self, planner=None, **kwargs) -> None:
        super().__init__(I.PLANNER_NODE, **kwargs)
        policy_path = declare(self, "policy_path", "", "policy checkpoint (.pt); empty: the shipped default")
        map_id = declare(self, "map_id", "dual_lane_4way", "the planner's map: a packaged id or a map YAML path")
        planner_class = declare(self, "planner_class", DEFAULT_CLASS, "a planner class: an entry point name of "
                                "group bimacppo.planners, or module:Class with load/reset/step")
        cache_size = declare(self, "cache_size", 64, "answers kept per stamp (re-sent ticks are answered from it)",
                             lo=1, hi=100_000)
        markers_on = declare(self, "publish_markers", True, "publish /planner/markers")
        jump_ns = int(declare(self, "max_stamp_jump_s", MAX_STAMP_JUMP_S, "a stamp further ahead of the newest "
                              "answered tick is a jump (docs/interfaces.md, tick protocol)",
                              lo=0.1, hi=3600.0) * I.NS_PER_S)
        selection = declare(self, "action_selection", "", "how the policy picks each head's action: argmax, or "
                            "median (the head's weighted median over its ordered values); empty: the way the "
                            "policy file says", choices=("", *HighLevelPlanner.SELECTIONS))
        # answers: stamp -> reference sent
        self.protocol = TickProtocol(cache_size, jump_ns, log=self._log, on_restart=self._clear_tick_caches)
        self.dropped: dict = {}          # topic -> messages dropped (bad content or stamp)
        if planner is None:
            planner = make_planner(planner_class, policy_path, map_id, selection)
        self.hp = planner
        self.road = getattr(self.hp, "road", None)
        self.frame = getattr(self.road, "frame", None) or MapFrame()
        self.markers_on = markers_on
        # the agent's own environment config: reward terms and decision period as in training
        cfg = getattr(self.hp, "cfg", None)
        if not isinstance(cfg, EnvConfig):
            cfg = EnvConfig.load()
        self.reward_cfg = cfg.reward
        self.decision_every = int(cfg.action.decision_every)
        self.states: OrderedDict = OrderedDict()
        self.objects: OrderedDict = OrderedDict()
        self.decisions_ep: list = []     # (stamp, lane_change) of each decision of the current episode
        self.ev_start = None             # the EV's (x, y) at the episode's first tick (map's own frame)
        self.ep_goal = None              # the goal of the episode whose decisions are held (map's own frame)
        self.sv_tracks: dict = {}        # SV id -> [first (x, y), last (x, y)] in the episode (map's own frame)
        self.ticks_ep = 0                # ticks answered in the current episode
        self.x_imr = None                # the decision held between decisions (decision_every > 1)
        self.decisions = 0
        self.returns: list = []          # episode returns published, in order (for in-process use)
        self.pub_ref = self.create_publisher(I.Odometry, I.TOPIC_REFERENCE, I.STATE_QOS)
        self.pub_markers = self.create_publisher(I.MarkerArray, I.TOPIC_PLANNER_MARKERS, I.MARKER_QOS)
        self.pub_result = self.create_publisher(I.DiagnosticStatus, I.TOPIC_PLANNER_RESULT, I.RESULT_QOS)
        sub = lambda typ, topic, fn, qos: self.create_subscription(  # noqa: E731
            typ, topic, guarded(self, topic, fn, self.dropped), qos)
        sub(I.PoseStamped, I.TOPIC_GOAL, self._on_goal, I.LATCHED_QOS)
        sub(I.DiagnosticStatus, I.TOPIC_RESULT, self._on_result, I.RESULT_QOS)
        sub(I.Odometry, I.TOPIC_EGO_ODOM, self._on_odom, I.STATE_QOS)
        sub(I.MultiDOFJointTrajectory, I.TOPIC_OBJECTS, self._on_objects, I.STATE_QOS)
        pol = getattr(self.hp, "policy", None)
        if pol is not None:    # which policy answers, and how it picks its actions, once at start
            m = getattr(pol, "meta", {}) or {}
            self.get_logger().info(
                f"policy {getattr(pol, 'path', '?')} (curriculum {m.get('curriculum', '?')}, seed "
                f"{m.get('seed', '?')}, {m.get('episodes', '?')} episodes), actions by "
                f"{getattr(self.hp, 'action_selection', '?')}, map {getattr(self.road, 'id', '?')}")

    def _log(self, level: str, msg: str) -> None:
        getattr(self.get_logger(), level)(msg)

    def _clear_tick_caches(self) -> None:
        self.states.clear(), self.objects.clear()
        self.decisions_ep, self.ticks_ep = [], 0
        self.ev_start, self.ep_goal, self.sv_tracks = None, None, {}

    def _n_pcp(self, facts: dict) -> None:
        """The source's n_pcp, else the one inferred from the planner's map (added to ``facts``)."""
        if "n_pcp" in facts or self.road is None or self.ev_start is None:
            return
        n = self.road.infer_n_pcp(self.ev_start, self.ep_goal[:2], [tuple(t) for t in self.sv_tracks.values()])
        if n is not None:
            facts["n_pcp"] = str(int(n))

    def _on_goal(self, msg) -> None:
        goal, stamp = I.pose_to_goal(msg), I.stamp_to_ns(msg.header.stamp)
        if self.protocol.on_goal(stamp, goal) in REFUSED:
            raise I.MessageError(self.protocol.reason)
        self._process()

    def _on_result(self, msg) -> None:
        res = I.status_to_result(msg)
        # the episode whose decisions are held starts at its first decision (the next goal
        # may already be here: DDS does not order result and goal across topics)
        start = self.decisions_ep[0][0] if self.decisions_ep else self.protocol.goal_stamp
        verdict = self.protocol.on_result(res.stamp_ns, start)
        if verdict in REFUSED:
            raise I.MessageError(self.protocol.reason)
        if verdict is not Verdict.ENDS:
            return
        flags = [c for s, c in self.decisions_ep if s < res.stamp_ns]
        facts = I.result_extras(msg)
        self._n_pcp(facts)
        try:
            ret = episode_return(flags, res.outcome, facts, self.reward_cfg)
        except (KeyError, ValueError) as exc:
            self.get_logger().warning(f"episode return not computed: {exc}")
            return
        if not np.isfinite(ret):   # the input facts are finite (status_to_result); the sum must be too
            self.get_logger().warning(f"episode return {ret} is not finite: not published")
            return
        self.returns.append(ret)
        out = I.DiagnosticStatus(level=msg.level, name=msg.name, message=msg.message,
                                 hardware_id=msg.hardware_id, values=list(msg.values))
        added = {"return": repr(ret)}
        if "n_pcp" not in I.result_extras(msg) and "n_pcp" in facts:
            added["n_pcp"] = facts["n_pcp"]
        out.values = [kv for kv in out.values if kv.key not in added] + \
            [I.KeyValue(key=k, value=v) for k, v in added.items()]
        self.pub_result.publish(out)

    def _on_odom(self, msg) -> None:
        x = I.odometry_to_state(msg)
        stamp = I.stamp_to_ns(msg.header.stamp)
        if self.protocol.on_state(stamp, x) in REFUSED:
            raise I.MessageError(self.protocol.reason)
        self.states[stamp] = x
        self.protocol.bound(self.states)
        self._process()

    def _on_objects(self, msg) -> None:
        ids, svs = I.objects_to_svs(msg)
        stamp = I.stamp_to_ns(msg.header.stamp)
        if self.protocol.on_input(stamp, "objects") in REFUSED:
            raise I.MessageError(self.protocol.reason)
        self.objects[stamp] = (ids, svs)
        self.protocol.bound(self.objects)
        self._process()

    def _process(self) -> None:
        p = self.protocol
        for stamp in sorted(set(self.states) & set(self.objects)):
            if p.cached(stamp) is not None:
                self.pub_ref.publish(p.cached(stamp))  # a re-sent tick: same answer
                del self.states[stamp], self.objects[stamp]
                continue
            kind = p.classify(stamp)
            if kind is Verdict.WAIT:
                continue
            ego_w, (ids, svs) = self.states.pop(stamp), self.objects.pop(stamp)
            if kind is Verdict.STALE:
                continue
            # the policy works in the map's own frame
            ego, svs = self.frame.states_to_map(ego_w), self.frame.states_to_map(svs)
            if p.start_episode():
                goal = self.frame.poses_to_map(np.asarray(p.goal, dtype=float))
                try:
                    self.hp.reset(ego, goal)
                except Exception as exc:  # noqa: BLE001 - e.g. no route to an implausible goal
                    self.get_logger().error(f"planner reset failed at {stamp} ns: {type(exc).__name__}: "
                                            f"{one_line(exc)}", throttle_duration_sec=1.0)
                    p.retry_start()  # retry the reset with the next state
                    continue
                self.decisions_ep, self.ticks_ep = [], 0
                self.ev_start, self.ep_goal, self.sv_tracks = ego[:2].copy(), goal, {}
            if not p.current(stamp):
                continue  # a newer stamp was answered meanwhile
            if self.ticks_ep % self.decision_every == 0:
                # as IntersectionEnv.step: one decision, held for decision_every ticks
                try:
                    x_imr, info = self.hp.step(ego, svs)
                    x_imr = np.asarray(x_imr, dtype=float)
                    if x_imr.shape != (4,) or not np.all(np.isfinite(x_imr)):
                        raise ValueError(f"policy returned x_IMR {x_imr.tolist()}")
                except Exception as exc:  # noqa: BLE001 - leave the tick unanswered, keep running
                    self.get_logger().error(f"planner step failed at {stamp} ns: {type(exc).__name__}: "
                                            f"{one_line(exc)}", throttle_duration_sec=1.0)
                    continue
                self.x_imr = x_imr
                self.decisions += 1
                self.decisions_ep.append((stamp, bool((info or {}).get("lane_change", False))))
            self.ticks_ep += 1
            for i, sv in zip(ids, svs):
                self.sv_tracks.setdefault(i, [sv[:2].copy(), None])[1] = sv[:2].copy()
            x_imr = self.frame.states_to_world(self.x_imr)
            ref = I.reference_to_odometry(x_imr, stamp)
            p.answered(stamp, ref, ego_w)
            self.pub_ref.publish(ref)
            if self.markers_on:
                self.pub_markers.publish(I.reference_markers(x_imr, stamp))


def main(argv=None) -> int:
    def make(args):
        if args:
            raise ValueError(f"planner_node takes no positional arguments (got {args})")
        return PlannerNode()
    return run_single(make, argv)


if __name__ == "__main__":
    raise SystemExit(main())
