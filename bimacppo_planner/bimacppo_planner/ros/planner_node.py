"""Planner node: the trained policy (``HighLevelPlanner``) between the world's state and x_IMR.

For each state stamp s that has both /ego/odom and /objects, it publishes
/planner/reference (x_IMR) stamped s. A new /goal_pose starts an episode
(``hp.reset(ego, goal)``: A* on the planner's own copy of the road map); repeats of a
stamp are answered from a cache, so the policy's internal state (waypoint tracker)
advances once per tick exactly as in the in-process loop.

When the world reports the end of the episode (/episode/result), the planner republishes
that result on /planner/episode_result with ``return`` added: the return is the agent's
(its reward function, docs/method.md), not a fact of the world, so it is computed here.
"""
from __future__ import annotations

import importlib
import pathlib
from collections import OrderedDict

import numpy as np
from rclpy.node import Node

from bimacppo_sim.ros import interfaces as I
from bimacppo_sim.ros.runtime import run_single

DEFAULT_CLASS = "bimacppo_planner.agent:HighLevelPlanner"


def load_class(spec: str):
    """``module:Class`` -> the class (ValueError naming what is missing)."""
    mod, _, name = spec.partition(":")
    if not mod or not name:
        raise ValueError(f"planner_class must look like 'package.module:Class', got {spec!r}")
    try:
        return getattr(importlib.import_module(mod), name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"planner_class {spec!r} is not importable: {exc}") from None


def default_policy_path() -> str:
    """The policy shipped inside bimacppo_planner (the agent module's DEFAULT_POLICY_PATH if set)."""
    try:
        agent = importlib.import_module("bimacppo_planner.agent")
        path = getattr(agent, "DEFAULT_POLICY_PATH", None)
        if path:
            return str(path)
    except ImportError:
        pass
    pkg = pathlib.Path(__file__).resolve().parents[1]
    found = sorted(pkg.rglob("*.pt"))
    if not found:
        raise ValueError(f"no policy_path given and no shipped policy (*.pt) under {pkg}")
    return str(found[0])


def episode_return(step_rewards, outcome: str, facts: dict, reward_cfg) -> float:
    """Sum of per-decision rewards + the terminal reward of eq. (26)-(28), as IntersectionEnv.step."""
    rc = reward_cfg
    n_sv = int(facts["n_sv"])
    total = float(sum(step_rewards))
    if outcome == "success":
        return total + rc.success_base + rc.alpha1 * n_sv + rc.alpha2 * int(facts.get("n_pcp", 0))
    d = max(float(facts.get("dist_to_goal", 1e-3)), 1e-3)
    total += min(rc.r_f_max, rc.alpha3 / d)
    if outcome == "collision":
        total += rc.collision_base + rc.alpha4 * n_sv * float(facts.get("speed", 0.0))
    elif outcome == "timeout":
        total += rc.timeout
    return total


class PlannerNode(Node):
    """Thin adapter over ``HighLevelPlanner.reset/step``."""

    def __init__(self, planner=None, **kwargs) -> None:
        super().__init__(I.PLANNER_NODE, **kwargs)
        self.declare_parameter("policy_path", "")
        self.declare_parameter("map_id", "dual_lane_4way")
        self.declare_parameter("planner_class", DEFAULT_CLASS)
        self.declare_parameter("cache_size", 64)
        self.declare_parameter("publish_markers", True)
        g = lambda n: self.get_parameter(n).value  # noqa: E731
        if planner is None:
            cls = load_class(g("planner_class"))
            path = g("policy_path") or (default_policy_path() if g("planner_class") == DEFAULT_CLASS else "")
            planner = cls.load(path, g("map_id"))
        self.hp = planner
        self.cache_size = int(g("cache_size"))
        self.markers_on = bool(g("publish_markers"))
        try:
            from bimacppo_planner.decision import EnvConfig
            self.reward_cfg = EnvConfig.load().reward
        except Exception as exc:  # the node still drives; only the return is unavailable
            self.get_logger().warning(f"no reward config ({exc}): episode returns not computed")
            self.reward_cfg = None
        self.gate = I.EpisodeGate()
        self.states: OrderedDict = OrderedDict()
        self.objects: OrderedDict = OrderedDict()
        self.answers: OrderedDict = OrderedDict()
        self.rewards: list = []          # (stamp, per-decision reward) of the current episode
        self.decisions = 0
        self.pub_ref = self.create_publisher(I.Odometry, I.TOPIC_REFERENCE, I.STATE_QOS)
        self.pub_markers = self.create_publisher(I.MarkerArray, I.TOPIC_PLANNER_MARKERS, I.MARKER_QOS)
        self.pub_result = self.create_publisher(I.DiagnosticStatus, I.TOPIC_PLANNER_RESULT, I.RESULT_QOS)
        self.create_subscription(I.PoseStamped, I.TOPIC_GOAL, self._on_goal, I.LATCHED_QOS)
        self.create_subscription(I.DiagnosticStatus, I.TOPIC_RESULT, self._on_result, I.RESULT_QOS)
        self.create_subscription(I.Odometry, I.TOPIC_EGO_ODOM, self._on_odom, I.STATE_QOS)
        self.create_subscription(I.MultiDOFJointTrajectory, I.TOPIC_OBJECTS, self._on_objects, I.STATE_QOS)

    def _bounded(self, d: OrderedDict) -> None:
        while len(d) > self.cache_size:
            d.popitem(last=False)

    def _on_goal(self, msg) -> None:
        try:
            goal = I.pose_to_goal(msg)
        except I.MessageError as exc:
            self.get_logger().warning(f"ignored goal: {exc}")
            return
        self.gate.on_goal(I.stamp_to_ns(msg.header.stamp), goal)
        self._process()

    def _on_result(self, msg) -> None:
        try:
            res = I.status_to_result(msg)
        except I.MessageError as exc:
            self.get_logger().warning(f"ignored episode result: {exc}")
            return
        was_active = self.gate.goal_stamp is not None and not self.gate.ended
        self.gate.on_result(res.stamp_ns)
        if not was_active or self.reward_cfg is None:
            return
        facts = I.result_extras(msg)
        steps = [r for s, r in self.rewards if s < res.stamp_ns]
        try:
            ret = episode_return(steps, res.outcome, facts, self.reward_cfg)
        except (KeyError, ValueError) as exc:
            self.get_logger().warning(f"episode return not computed: {exc}")
            return
        out = I.DiagnosticStatus(level=msg.level, name=msg.name, message=msg.message,
                                 hardware_id=msg.hardware_id, values=list(msg.values))
        out.values = [kv for kv in out.values if kv.key != "return"] + [I.KeyValue(key="return", value=repr(ret))]
        self.pub_result.publish(out)

    def _on_odom(self, msg) -> None:
        try:
            self.states[I.stamp_to_ns(msg.header.stamp)] = I.odometry_to_state(msg)
        except I.MessageError as exc:
            self.get_logger().warning(f"ignored state: {exc}")
            return
        self._bounded(self.states)
        self._process()

    def _on_objects(self, msg) -> None:
        try:
            _, svs = I.objects_to_svs(msg)
        except I.MessageError as exc:
            self.get_logger().warning(f"ignored objects: {exc}")
            return
        self.objects[I.stamp_to_ns(msg.header.stamp)] = svs
        self._bounded(self.objects)
        self._process()

    def _process(self) -> None:
        for stamp in sorted(set(self.states) & set(self.objects)):
            if stamp in self.answers:
                self.pub_ref.publish(self.answers[stamp])  # a re-sent tick: same answer
                del self.states[stamp], self.objects[stamp]
                continue
            kind = self.gate.classify(stamp)
            if kind == "wait":
                continue
            ego, svs = self.states.pop(stamp), self.objects.pop(stamp)
            if kind == "stale":
                continue
            if self.gate.new_episode():
                self.hp.reset(ego, np.asarray(self.gate.goal, dtype=float))
                self.rewards = []
            x_imr, info = self.hp.step(ego, svs)
            self.decisions += 1
            if self.reward_cfg is not None:
                changed = bool((info or {}).get("lane_change", (info or {}).get("changed", False)))
                self.rewards.append((stamp, self.reward_cfg.step + (self.reward_cfg.lane_change if changed else 0.0)))
            ref = I.reference_to_odometry(x_imr, stamp)
            self.answers[stamp] = ref
            self._bounded(self.answers)
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
