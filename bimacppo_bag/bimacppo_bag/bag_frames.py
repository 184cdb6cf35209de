"""A recording as bird's-eye frames: what ``bimacppo-sim render-bag`` draws, one frame per state.

The bag (an MCAP file or a rosbag2 directory, any writer) is read with ``mcap_io.iter_mcap``
(log-time order, damaged chunks skipped and reported) and every message goes through the
converters of :mod:`bimacppo_interfaces.contract`, so a frame shows exactly what a node of the graph would have
received. Rules:

* one frame per distinct ``/ego/odom`` stamp (a lockstep re-send repeats a stamp: drawn once);
  a bag without ``/ego/odom`` cannot be rendered (:class:`BagRenderError`);
* SVs: the ``/objects`` of the same stamp, else the latest earlier one (a source may publish
  them less often); x_IMR: the ``/planner/reference`` of the same stamp only (it answers that
  state); goal and route: the latest at or before the state (the goal is latched per episode,
  the route is the world's ``/objects/markers`` LINE_STRIP ``route``);
* the episode a frame belongs to runs from its goal's stamp to the next ``/episode/result``'s
  ``stamp_ns``: time on the frame is counted from the goal, and the terminal frame shows the
  outcome; the task comes from that result;
* a topic recorded with another type than the contract's, and a message the converters reject,
  are skipped and counted in :class:`BagFrames` ``skipped`` (the caller warns), never guessed;
* the map: what our recorder wrote in its ``bimacppo`` metadata record (``map_id``, and
  ``map_yaml`` for a map file), else ``""``: a bag of another writer names no map, and which map
  to draw it on is the caller's choice.
"""
from __future__ import annotations

import bisect
import os
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional

import numpy as np
from rclpy.serialization import deserialize_message

from bimacppo_interfaces import contract as I

from . import mcap_io

TOPICS = {   # topic -> message class; /ego/odom is the one a frame needs
    I.TOPIC_EGO_ODOM: I.Odometry,
    I.TOPIC_OBJECTS: I.MultiDOFJointTrajectory,
    I.TOPIC_REFERENCE: I.Odometry,
    I.TOPIC_GOAL: I.PoseStamped,
    I.TOPIC_MARKERS: I.MarkerArray,
    I.TOPIC_RESULT: I.DiagnosticStatus,
}


class BagRenderError(ValueError):
    """A bag that cannot be rendered (names the path and the reason, one line)."""


@dataclass
class Frame:
    stamp_ns: int
    ego: np.ndarray                   # [x, y, v, psi]
    svs: np.ndarray                   # (n, 4)
    sv_ids: List[str]
    x_imr: Optional[np.ndarray]       # [x, y, v, psi] or None
    goal: Optional[np.ndarray]        # [x, y, psi] or None
    route: Optional[np.ndarray]       # (M, 2) or None
    time_s: float                     # since the episode's goal (its first state)
    task: str = ""
    outcome: Optional[str] = None     # on the terminal frame of an episode


@dataclass
class BagFrames:
    frames: List[Frame]
    messages: Dict[str, int] = field(default_factory=dict)   # every topic of the bag: messages read
    skipped: Dict[str, str] = field(default_factory=dict)    # topic -> why (some or all of it)
    damaged: str = ""                                        # the reader's report when it skipped data
    map_id: str = ""                                         # the recorded world's map_id ("" = not recorded)
    map_yaml: str = ""                                       # the text of that map file, if recorded


def _same_type(a: str, b: str) -> bool:
    try:
        return mcap_io.split_type(a) == mcap_io.split_type(b)
    except mcap_io.DefinitionNotFound:
        return False


def _latest(stamps: List[int], items: list, stamp: int):
    i = bisect.bisect_right(stamps, stamp) - 1
    return items[i] if i >= 0 else None


def read_bag(path, progress: Optional[Callable[[int], None]] = None) -> BagFrames:
    """The frames of a bag. ``progress(n)`` is called as messages are read (n since the last call)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise BagRenderError(f"no such file: {path}")
    try:
        files, _ = mcap_io.bag_files(path)
    except (mcap_io.BagError, FileNotFoundError) as exc:
        raise BagRenderError(str(exc)) from None
    raw: Dict[str, list] = {t: [] for t in TOPICS}
    skipped: Dict[str, str] = {}
    counts: Dict[str, int] = {}
    problems = []
    run: Dict[str, str] = {}   # the recorder's run metadata: the last file that has it
    for f in files:
        report = mcap_io.ReadReport()
        for schema, channel, msg in mcap_io.iter_mcap(f, report):
            if progress is not None:
                progress(1)
            topic = channel.topic
            if topic not in TOPICS:
                continue
            type_name = schema.name if schema is not None else ""
            if not _same_type(type_name, I.TOPIC_TYPES[topic]) or channel.message_encoding != mcap_io.MESSAGE_ENCODING:
                skipped[topic] = (f"recorded as {type_name or '?'} ({channel.message_encoding}), "
                                  f"expected {I.TOPIC_TYPES[topic]} (cdr)")
                continue
            raw[topic].append(msg.data)
        for t, n in report.topics.items():
            counts[t] = counts.get(t, 0) + n
        run = dict(report.metadata.get(mcap_io.RUN_METADATA) or run)
        if not report.complete:
            if report.messages == 0:
                raise BagRenderError(f"{f} is not a readable MCAP file ({report.error})")
            problems.append(f"{os.path.basename(f)}: {report.error}")
    if not raw[I.TOPIC_EGO_ODOM]:
        have = ", ".join(sorted(counts)) or "no messages at all"
        why = f" ({skipped[I.TOPIC_EGO_ODOM]})" if I.TOPIC_EGO_ODOM in skipped else ""
        raise BagRenderError(f"{path} has no usable {I.TOPIC_EGO_ODOM} messages (the EV state){why}; "
                             f"the bag holds: {have}")
    rejected: Dict[str, int] = {}

    def convert(topic, fn):
        out = []
        for data in raw[topic]:
            try:
                out.append(fn(deserialize_message(data, TOPICS[topic])))
            except Exception:   # noqa: BLE001 - undecodable bytes or a value the contract rejects
                rejected[topic] = rejected.get(topic, 0) + 1
        raw[topic] = []
        return sorted(out, key=lambda item: item[0])   # stable: file (log-time) order within a stamp

    def stamped(fn):
        return lambda m: (I.stamp_to_ns(m.header.stamp), fn(m))

    def route(m):   # every marker of the array carries the tick's stamp
        pts = I.route_from_markers(m.markers)
        return (I.stamp_to_ns(m.markers[0].header.stamp), pts) if pts is not None else (-1, None)

    def result(m):
        res = I.status_to_result(m)
        return (res.stamp_ns, (res.task, res.outcome))

    egos = convert(I.TOPIC_EGO_ODOM, stamped(I.odometry_to_state))
    objects = convert(I.TOPIC_OBJECTS, stamped(I.objects_to_svs))
    refs = dict(convert(I.TOPIC_REFERENCE, stamped(I.odometry_to_reference)))
    goals = convert(I.TOPIC_GOAL, stamped(I.pose_to_goal))
    routes = [r for r in convert(I.TOPIC_MARKERS, route) if r[1] is not None]
    results = convert(I.TOPIC_RESULT, result)
    for topic, n in rejected.items():
        skipped.setdefault(topic, f"{n} message(s) rejected by the converters")
    if not egos:
        raise BagRenderError(f"{path}: all {rejected.get(I.TOPIC_EGO_ODOM, 0)} {I.TOPIC_EGO_ODOM} messages "
                             "were rejected by the converters (docs/interfaces.md: frame map, finite values)")

    o_st, g_st, r_st = [s for s, _ in objects], [s for s, _ in goals], [s for s, _ in routes]
    res_st = [s for s, _ in results]
    frames, seen = [], set()
    for stamp, ego in egos:
        if stamp in seen:
            continue
        seen.add(stamp)
        obj = _latest(o_st, objects, stamp)
        ids, svs = (obj[1][0], obj[1][1]) if obj is not None else ([], np.zeros((0, 4)))
        goal = _latest(g_st, goals, stamp)
        rt = _latest(r_st, routes, stamp)
        i = bisect.bisect_left(res_st, stamp)               # the result that ends this frame's episode
        res = results[i][1] if i < len(results) else None
        start = goal[0] if goal is not None else egos[0][0]
        frames.append(Frame(stamp_ns=stamp, ego=ego, svs=svs, sv_ids=list(ids), x_imr=refs.get(stamp),
                            goal=goal[1] if goal is not None else None, route=rt[1] if rt is not None else None,
                            time_s=(stamp - start) / I.NS_PER_S, task=res[0] if res else "",
                            outcome=res[1] if res is not None and res_st[i] == stamp else None))
    return BagFrames(frames=frames, messages=counts, skipped=skipped, damaged="; ".join(problems),
                     map_id=run.get(mcap_io.MAP_ID_KEY, ""), map_yaml=run.get(mcap_io.MAP_YAML_KEY, ""))
