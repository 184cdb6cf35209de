"""Helpers of the fault-injection suite (tests/test_faults.py): processes, a watcher, a ledger.

The watcher subscribes *raw* to every output topic of every node and decodes each message
itself, so a message the test injected (same topic, e.g. a NaN on /ego/odom) is recognised
by its value and not blamed on a node.
"""
from __future__ import annotations

import array
import json
import math
import os
import pathlib
import signal
import subprocess
import sys
import time
from collections import defaultdict

import rclpy
from rclpy.serialization import deserialize_message, serialize_message

from bimacppo_interfaces import contract as I
from rosgraph_msgs.msg import Clock as ClockMsg

# PYTHONFAULTHANDLER: a node that hangs is sent SIGABRT (communicate_or_dump) and prints every
# thread's stack, so a hang found under load says where it was.
ENV = dict(os.environ, AMENT_PREFIX_PATH=os.environ.get("AMENT_PREFIX_PATH", sys.prefix),
           PYTHONUNBUFFERED="1", PYTHONFAULTHANDLER="1")

OUTPUTS = {   # every output topic of every node
    I.TOPIC_CLOCK: ClockMsg, I.TOPIC_EGO_ODOM: I.Odometry, I.TOPIC_OBJECTS: I.MultiDOFJointTrajectory,
    I.TOPIC_MARKERS: I.MarkerArray, I.TOPIC_GOAL: I.PoseStamped, I.TOPIC_RESULT: I.DiagnosticStatus,
    I.TOPIC_REFERENCE: I.Odometry, I.TOPIC_PLANNER_MARKERS: I.MarkerArray,
    I.TOPIC_COMMAND: I.JointTrajectory, I.TOPIC_PLANNER_RESULT: I.DiagnosticStatus,
}
QOS = {I.TOPIC_CLOCK: I.CLOCK_QOS, I.TOPIC_GOAL: I.LATCHED_QOS, I.TOPIC_RESULT: I.RESULT_QOS,
       I.TOPIC_PLANNER_RESULT: I.RESULT_QOS, I.TOPIC_MARKERS: I.MARKER_QOS,
       I.TOPIC_PLANNER_MARKERS: I.MARKER_QOS}


def non_finite(msg, path: str = "") -> list:
    """Paths of every non-finite float in a ROS message, walking its fields generically
    (``get_fields_and_field_types``), nested messages and arrays included; string values
    of DiagnosticStatus key-values that parse as floats are checked too (the return)."""
    out = []
    if isinstance(msg, float):
        return [] if math.isfinite(msg) else [path]
    if isinstance(msg, str):
        if path.endswith(".value"):
            try:
                v = float(msg)
            except ValueError:
                return []
            return [] if math.isfinite(v) else [path]
        return []
    if isinstance(msg, (list, tuple, array.array)) or type(msg).__name__ == "ndarray":
        for i, v in enumerate(msg):
            out += non_finite(v if not hasattr(v, "item") or hasattr(v, "get_fields_and_field_types")
                              else v.item(), f"{path}[{i}]")
        return out
    if hasattr(msg, "get_fields_and_field_types"):
        for name in msg.get_fields_and_field_types():
            out += non_finite(getattr(msg, name), f"{path}.{name}")
    return out


class Watcher:
    """Raw subscriber to every output topic; records progress and any non-finite value."""

    def __init__(self, node, executor=None):
        self.node = node
        self.executor = executor       # for a node in its own context (another DDS domain)
        self.injected = set()          # repr of every message the test published itself
        self.injected_topics = set()
        self.bad = []                  # (topic, paths) of non-finite values from nodes
        self.counts = defaultdict(int)
        self.commands = []             # (wall monotonic, stamp, a, delta, n_points)
        self.answered = set()          # command stamps that equal a state stamp seen
        self.states = set()
        self.speeds = []               # (wall monotonic, stamp, v) of every EV state from the world
        self.last = {}                 # topic -> last message from a node
        self.on_result = None          # called on every /episode/result (e.g. to reset the world)
        for topic, typ in OUTPUTS.items():
            node.create_subscription(typ, topic, lambda raw, t=topic, ty=typ: self._on(t, ty, raw),
                                     QOS.get(topic, I.STATE_QOS), raw=True)

    def _on(self, topic, typ, raw) -> None:
        msg = deserialize_message(raw, typ)
        bad = non_finite(msg)
        if topic in self.injected_topics and repr(msg) in self.injected:
            return  # our own injection (compared by value: CDR padding bytes may differ)
        self.counts[topic] += 1
        self.last[topic] = msg
        if bad:
            self.bad.append((topic, bad[:5]))
        if topic == I.TOPIC_RESULT and self.on_result is not None:
            self.on_result()
        if topic == I.TOPIC_EGO_ODOM:
            self.states.add(I.stamp_to_ns(msg.header.stamp))
            self.speeds.append((time.monotonic(), I.stamp_to_ns(msg.header.stamp), msg.twist.twist.linear.x))
        elif topic == I.TOPIC_COMMAND and msg.points:
            st = msg.header.stamp.sec * I.NS_PER_S + msg.header.stamp.nanosec
            p0 = msg.points[0]
            self.commands.append((time.monotonic(), st, p0.accelerations[1], p0.positions[0], len(msg.points)))
            if st in self.states:
                self.answered.add(st)

    def publish(self, pub, msg) -> None:
        self.injected.add(repr(deserialize_message(serialize_message(msg), type(msg))))
        self.injected_topics.add(pub.topic_name)
        pub.publish(msg)

    def spin(self, seconds: float, until=None) -> bool:
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            if until is not None and until():
                return True
            if self.executor is not None:
                self.executor.spin_once(timeout_sec=0.02)
            else:
                rclpy.spin_once(self.node, timeout_sec=0.02)
        return bool(until and until())

    def progress(self, ticks: int = 3, timeout: float = 20.0, after: int = -1) -> bool:
        """The loop answers ``ticks`` world states published from now on (distinct stamps,
        stamped after ``after``) within timeout. Counted among the states of this window, not
        against every stamp ever answered: a restarted world publishes its old stamps again."""
        n_cmd, n_st = len(self.commands), len(self.speeds)

        def answered():
            states = {st for _, st, _ in self.speeds[n_st:]}
            return len({st for _, st, *_ in self.commands[n_cmd:] if st in states and st > after})
        return self.spin(timeout, lambda: answered() >= ticks)


def start(*args, log=None, env=None):
    return subprocess.Popen([sys.executable, *args], env=env or ENV, stdout=log or subprocess.DEVNULL,
                            stderr=subprocess.STDOUT, text=True)


def stop(procs, sig=signal.SIGINT, timeout=15.0) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(sig)
    for p in procs:
        try:
            p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def communicate_or_dump(p, timeout: float):
    """``p.communicate(timeout)``; a process still running then gets SIGABRT, which the fault
    handler (ENV) answers by writing all threads' stacks to stderr before it dies, and that
    stderr is returned with the rest. Returns (stdout, stderr, hung)."""
    try:
        out, err = p.communicate(timeout=timeout)
        return out, err, False
    except subprocess.TimeoutExpired:
        p.send_signal(signal.SIGABRT)
        try:
            out, err = p.communicate(timeout=10.0)
        except subprocess.TimeoutExpired:
            p.kill()
            out, err = p.communicate()
        return out, err, True


def log_lines(path, needle: str) -> int:
    """Lines of a process log that contain ``needle``."""
    return sum(1 for line in pathlib.Path(path).read_text().splitlines() if needle in line)


class Ledger:
    """Every case tried and whether it held; printed and written as JSON at the end."""

    def __init__(self):
        self.cases = []     # (group, name, held, detail)

    def record(self, group: str, name: str, held: bool, detail: str = "") -> bool:
        self.cases.append((group, name, bool(held), detail))
        return bool(held)

    def failed(self, group: str) -> list:
        return [(n, d) for g, n, h, d in self.cases if g == group and not h]

    def summary(self) -> str:
        held = sum(1 for c in self.cases if c[2])
        return f"fault-injection: {len(self.cases)} cases tried, {held} held"

    def write(self, path) -> None:
        with open(path, "w") as f:
            json.dump({"summary": self.summary(), "tried": len(self.cases),
                       "held": sum(1 for c in self.cases if c[2]),
                       "cases": [dict(group=g, name=n, held=h, detail=d) for g, n, h, d in self.cases]},
                      f, indent=1)
