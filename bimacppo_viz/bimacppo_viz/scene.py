"""The live view's scene: graph states (numpy, sim-time stamps in ns) -> Foxglove messages.

Inputs are what ``bimacppo_interfaces.contract`` converters return (``[x, y, v, psi]`` in the
``map`` frame, SV ids + ``(n, 4)`` states, ``[x, y, psi]`` goal, ``[a, delta]`` command with
its horizon), so every message convention is decided there and nowhere here. This module
imports no rclpy: it is unit-testable anywhere ``foxglove-sdk`` is installed.

Channels (the names the shipped layout opens):

* 3D scene, ``foxglove.SceneUpdate`` (protobuf): ``/viz/road`` (lane centrelines of the map),
  ``/viz/vehicles`` (EV + SVs, every update replaces the whole set so vanished SVs disappear),
  ``/viz/route``, ``/viz/reference`` (x_IMR), ``/viz/goal``;
* ``/viz/tf``, ``foxglove.FrameTransforms``: ``map -> base_link`` (EV) and ``map -> x_imr``,
  so the 3D panel can follow the EV;
* plots, JSON: ``/viz/ego`` and ``/viz/reference_state`` (``t, x, y, v, psi``),
  ``/viz/command`` (``t, a, delta`` and the MPC horizon), ``/viz/episode`` (one message per
  episode result: the world's as soon as the episode ends, then the planner's with the
  episode's ``return``, which only the agent can compute).

Entities and transforms carry the sim stamp of the state they show, so a transform lookup at
an entity's time finds the transform of the same tick. Display sizes and colours come from a
style object with the attributes of ``interfaces.MarkerStyle`` (body from the vehicle config),
which the world's RViz markers use too.
"""
from __future__ import annotations

import math
from typing import Mapping, Optional, Sequence

import numpy as np
from foxglove import messages as fm

# interfaces.FRAME_MAP / FRAME_BASE / FRAME_REFERENCE, which this module cannot import (rclpy);
# tests/test_viz_scene.py holds them equal
FRAME_MAP = "map"
FRAME_EGO = "base_link"
FRAME_REFERENCE = "x_imr"

CH_ROAD = "/viz/road"
CH_VEHICLES = "/viz/vehicles"
CH_ROUTE = "/viz/route"
CH_REFERENCE = "/viz/reference"
CH_GOAL = "/viz/goal"
CH_TF = "/viz/tf"
CH_EGO = "/viz/ego"
CH_REFERENCE_STATE = "/viz/reference_state"
CH_COMMAND = "/viz/command"
CH_EPISODE = "/viz/episode"
SCENE_CHANNELS = (CH_ROAD, CH_VEHICLES, CH_ROUTE, CH_REFERENCE, CH_GOAL)
JSON_CHANNELS = (CH_EGO, CH_REFERENCE_STATE, CH_COMMAND, CH_EPISODE)
CHANNELS = (*SCENE_CHANNELS, CH_TF, *JSON_CHANNELS)

# who sent an episode result: the world (/episode/result, no return) or the planner
# (/planner/episode_result, the world's facts plus the agent's return)
SOURCE_WORLD = "world"
SOURCE_PLANNER = "planner"
EPISODE_SOURCES = (SOURCE_WORLD, SOURCE_PLANNER)

ENTITY_ROAD = "road"
ENTITY_EGO = "ego"
ENTITY_SV_PREFIX = "sv/"
ENTITY_ROUTE = "route"
ENTITY_REFERENCE = "x_imr"
ENTITY_GOAL = "goal"

ARROW_LENGTH_M = 2.0      # x_IMR and goal arrows: heading only, drawn at one readable size
LABEL_SIZE_M = 1.2        # text labels (SV ids, EV speed) in scene metres
LANE_RGBA = (1.0, 1.0, 1.0, 0.6)          # straight lanes' centrelines
CONNECTOR_RGBA = (1.0, 1.0, 1.0, 0.25)    # the junction's connector lanes
LANE_LINE_WIDTH_M = 0.1

_STATE_SCHEMA = {
    "type": "object",
    "properties": {k: {"type": "number"} for k in ("t", "x", "y", "v", "psi")},
}
JSON_SCHEMAS = {
    CH_EGO: {**_STATE_SCHEMA, "title": "bimacppo.EgoState"},
    CH_REFERENCE_STATE: {**_STATE_SCHEMA, "title": "bimacppo.Reference"},
    CH_COMMAND: {
        "title": "bimacppo.Command",
        "type": "object",
        "properties": {
            "t": {"type": "number"}, "a": {"type": "number"}, "delta": {"type": "number"},
            "horizon_a": {"type": "array", "items": {"type": "number"}},
            "horizon_delta": {"type": "array", "items": {"type": "number"}},
        },
    },
    CH_EPISODE: {
        "title": "bimacppo.EpisodeResult",
        "type": "object",
        "properties": {"t": {"type": "number"}, "source": {"type": "string", "enum": list(EPISODE_SOURCES)},
                       "outcome": {"type": "string"},
                       "return": {"type": "number"},   # only in the planner's results
                       "values": {"type": "object", "additionalProperties": {"type": "string"}}},
        "required": ["t", "source", "outcome", "values"],
    },
}


# ----------------------------------------------------------------------------- primitives
def timestamp(stamp_ns: int) -> fm.Timestamp:
    if stamp_ns < 0:
        raise ValueError(f"stamp must be >= 0 ns, got {stamp_ns}")
    return fm.Timestamp(int(stamp_ns) // 1_000_000_000, int(stamp_ns) % 1_000_000_000)


def _seconds(stamp_ns: int) -> float:
    return int(stamp_ns) / 1e9


def yaw_quaternion(psi: float) -> fm.Quaternion:
    """Yaw-only rotation about +z (the convention of docs/interfaces.md)."""
    return fm.Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * psi), w=math.cos(0.5 * psi))


def _color(rgba) -> fm.Color:
    r, g, b, a = (float(c) for c in rgba)
    return fm.Color(r=r, g=g, b=b, a=a)


def _pose(x: float, y: float, z: float, psi: float) -> fm.Pose:
    return fm.Pose(position=fm.Vector3(x=float(x), y=float(y), z=float(z)), orientation=yaw_quaternion(float(psi)))


def _state(state, what: str) -> np.ndarray:
    s = np.asarray(state, dtype=float).reshape(-1)
    if s.shape != (4,) or not np.all(np.isfinite(s)):
        raise ValueError(f"{what}: expected 4 finite values [x, y, v, psi], got {state!r}")
    return s


def _body(state, style, rgba) -> fm.CubePrimitive:
    x, y, _, psi = state
    return fm.CubePrimitive(pose=_pose(x, y, 0.5 * style.height, psi),
                            size=fm.Vector3(x=float(style.length), y=float(style.width), z=float(style.height)),
                            color=_color(rgba))


def _label(x: float, y: float, z: float, text: str) -> fm.TextPrimitive:
    return fm.TextPrimitive(pose=_pose(x, y, z, 0.0), billboard=True, font_size=LABEL_SIZE_M,
                            scale_invariant=False, color=fm.Color(r=1.0, g=1.0, b=1.0, a=1.0), text=text)


def _arrow(x: float, y: float, z: float, psi: float, rgba) -> fm.ArrowPrimitive:
    return fm.ArrowPrimitive(pose=_pose(x, y, z, psi), shaft_length=0.7 * ARROW_LENGTH_M, shaft_diameter=0.3,
                             head_length=0.3 * ARROW_LENGTH_M, head_diameter=0.7, color=_color(rgba))


# ----------------------------------------------------------------------------- scene updates
def vehicles_update(ego, sv_ids: Sequence[str], sv_states, stamp_ns: int, style) -> fm.SceneUpdate:
    """EV and every SV as boxes; deletes all earlier entities of the channel first."""
    ts = timestamp(stamp_ns)
    ego = _state(ego, "ego")
    arr = np.asarray(sv_states, dtype=float).reshape(-1, 4) if len(sv_ids) else np.zeros((0, 4))
    if len(arr) != len(sv_ids):
        raise ValueError(f"{len(sv_ids)} SV ids but {len(arr)} SV states")
    if not np.all(np.isfinite(arr)):
        raise ValueError("SV states: non-finite value")
    entities = [fm.SceneEntity(timestamp=ts, frame_id=FRAME_MAP, id=ENTITY_EGO,
                               cubes=[_body(ego, style, style.ego_rgba)],
                               texts=[_label(ego[0], ego[1], style.height + 1.0, f"EV {ego[2]:.1f} m/s")])]
    for sid, s in zip(sv_ids, arr):
        entities.append(fm.SceneEntity(timestamp=ts, frame_id=FRAME_MAP, id=ENTITY_SV_PREFIX + str(sid),
                                       cubes=[_body(s, style, style.sv_rgba)],
                                       texts=[_label(s[0], s[1], style.height + 1.0, str(sid))]))
    return fm.SceneUpdate(deletions=[fm.SceneEntityDeletion(timestamp=ts, type=fm.SceneEntityDeletionType.All)],
                          entities=entities)


def _polyline(points, what: str) -> np.ndarray:
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] < 2 or len(pts) < 2 or not np.all(np.isfinite(pts[:, :2])):
        raise ValueError(f"{what}: expected >= 2 finite points (M, 2), got shape {pts.shape}")
    return pts


def _line(pts, z: float, width: float, rgba) -> fm.LinePrimitive:
    return fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, pose=_pose(0.0, 0.0, 0.0, 0.0),
                            thickness=float(width), scale_invariant=False,
                            points=[fm.Point3(x=float(p[0]), y=float(p[1]), z=z) for p in pts],
                            color=_color(rgba))


def road_update(lanes: Sequence[tuple]) -> fm.SceneUpdate:
    """The map's lanes ``[(kind, (N, 2) centreline), ...]`` as line strips: connectors (kind
    ``conn``) fainter than the straight lanes. Static: stamped 0."""
    lines = [_line(_polyline(pts, f"lane {i}"), 0.02, LANE_LINE_WIDTH_M,
                   CONNECTOR_RGBA if kind == "conn" else LANE_RGBA) for i, (kind, pts) in enumerate(lanes)]
    return fm.SceneUpdate(entities=[fm.SceneEntity(timestamp=timestamp(0), frame_id=FRAME_MAP, id=ENTITY_ROAD,
                                                   lines=lines)])


def route_update(points, stamp_ns: int, style) -> fm.SceneUpdate:
    """The EV's reference route (``(M, >= 2)`` array, x and y used) as one line strip."""
    line = _line(_polyline(points, "route"), 0.05, style.line_width, style.route_rgba)
    return fm.SceneUpdate(entities=[fm.SceneEntity(timestamp=timestamp(stamp_ns), frame_id=FRAME_MAP,
                                                   id=ENTITY_ROUTE, lines=[line])])


def reference_update(x_imr, stamp_ns: int, style) -> fm.SceneUpdate:
    """x_IMR as an arrow along its heading, with its speed as a label."""
    x, y, v, psi = _state(x_imr, "x_IMR")
    return fm.SceneUpdate(entities=[fm.SceneEntity(
        timestamp=timestamp(stamp_ns), frame_id=FRAME_MAP, id=ENTITY_REFERENCE,
        arrows=[_arrow(x, y, 0.2, psi, style.reference_rgba)],
        texts=[_label(x, y, 1.5, f"x_IMR {v:.1f} m/s")])])


def goal_update(goal, stamp_ns: int, style) -> fm.SceneUpdate:
    g = np.asarray(goal, dtype=float).reshape(-1)
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise ValueError(f"goal: expected 3 finite values [x, y, psi], got {goal!r}")
    return fm.SceneUpdate(entities=[fm.SceneEntity(
        timestamp=timestamp(stamp_ns), frame_id=FRAME_MAP, id=ENTITY_GOAL,
        arrows=[_arrow(g[0], g[1], 0.1, g[2], style.goal_rgba)],
        spheres=[fm.SpherePrimitive(pose=_pose(g[0], g[1], 0.1, 0.0), size=fm.Vector3(x=1.0, y=1.0, z=0.2),
                                    color=_color(style.goal_rgba))])])


def transform(child: str, state, stamp_ns: int) -> fm.FrameTransform:
    s = _state(state, child)
    return fm.FrameTransform(timestamp=timestamp(stamp_ns), parent_frame_id=FRAME_MAP, child_frame_id=child,
                             translation=fm.Vector3(x=float(s[0]), y=float(s[1]), z=0.0),
                             rotation=yaw_quaternion(float(s[3])))


# ----------------------------------------------------------------------------- JSON (plots)
def state_json(state, stamp_ns: int) -> dict:
    x, y, v, psi = (float(c) for c in _state(state, "state"))
    return {"t": _seconds(stamp_ns), "x": x, "y": y, "v": v, "psi": psi}


def command_json(u, horizon, stamp_ns: int) -> dict:
    """``u = [a, delta]``; ``horizon`` the ``(K, 2)`` rows of all points (row 0 = u)."""
    a, delta = (float(c) for c in np.asarray(u, dtype=float).reshape(2))
    h = np.asarray(horizon, dtype=float).reshape(-1, 2)
    if not (math.isfinite(a) and math.isfinite(delta) and np.all(np.isfinite(h))):
        raise ValueError("command: non-finite value")
    return {"t": _seconds(stamp_ns), "a": a, "delta": delta,
            "horizon_a": [float(r[0]) for r in h], "horizon_delta": [float(r[1]) for r in h]}


def episode_json(values: Mapping[str, str], stamp_ns: int, source: str = SOURCE_WORLD,
                 episode_return: Optional[float] = None) -> dict:
    """An episode result's key-values; ``return`` (a number, for plots) only when the source
    gives one: a world's result carries none, so a missing return is never shown as 0."""
    if source not in EPISODE_SOURCES:
        raise ValueError(f"episode result: source must be one of {EPISODE_SOURCES}, got {source!r}")
    out = {"t": _seconds(stamp_ns), "source": source, "outcome": str(values.get("outcome", "")),
           "values": {str(k): str(v) for k, v in values.items()}}
    if episode_return is not None:
        ret = float(episode_return)
        if not math.isfinite(ret):
            raise ValueError(f"episode result: return is not finite ({episode_return!r})")
        out["return"] = ret
    return out


# ----------------------------------------------------------------------------- the live scene
class LiveScene:
    """The live view's channels in one Foxglove context, and what to log on each.

    ``on_*`` take converted inputs (see the module docstring) and log on the matching
    channels. The EV and SV boxes are one update: ``on_state`` and ``on_objects`` each keep
    their latest input, and the vehicles are drawn once per tick, when both carry the same
    stamp (a source stamps both with the tick; DDS orders topics independently), so the EV of
    one tick never shows beside the SVs of another. Until a first ``/objects`` arrives the EV
    is drawn alone.
    """

    def __init__(self, context, style) -> None:
        from foxglove import Channel
        from foxglove.channels import FrameTransformsChannel, SceneUpdateChannel

        self.style = style
        self.scene = {name: SceneUpdateChannel(name, context=context) for name in SCENE_CHANNELS}
        self.tf = FrameTransformsChannel(CH_TF, context=context)
        self.json = {name: Channel(name, schema=JSON_SCHEMAS[name], context=context) for name in JSON_CHANNELS}
        self._ego: Optional[tuple] = None        # (stamp, state)
        self._objects: Optional[tuple] = None    # (stamp, ids, states)
        self._drawn: Optional[tuple] = None      # (stamp, with SVs) of the vehicles last drawn
        self._latched: dict = {}                 # channel -> its last message, for later clients
        self.logged = {name: 0 for name in CHANNELS}

    def _log(self, name: str, msg) -> None:
        (self.scene.get(name) or self.json.get(name) or self.tf).log(msg)
        self.logged[name] += 1

    def _vehicles(self) -> None:
        if self._ego is None:
            return
        stamp, ego = self._ego
        if self._objects is None:
            pair = ([], np.zeros((0, 4)))          # no SV source (yet): the EV alone
        elif self._objects[0] == stamp:
            pair = (self._objects[1], self._objects[2])
        else:
            return                                 # the SVs of another tick: wait for the match
        drawn = (stamp, self._objects is not None)
        if self._drawn == drawn:
            return
        self._log(CH_VEHICLES, vehicles_update(ego, pair[0], pair[1], stamp, self.style))
        self._drawn = drawn

    def on_state(self, state, stamp_ns: int) -> None:
        self._ego = (int(stamp_ns), _state(state, "ego"))
        self._log(CH_EGO, state_json(state, stamp_ns))
        self._log(CH_TF, fm.FrameTransforms(transforms=[transform(FRAME_EGO, state, stamp_ns)]))
        self._vehicles()

    def on_objects(self, ids: Sequence[str], states, stamp_ns: int) -> None:
        self._objects = (int(stamp_ns), list(ids), np.asarray(states, dtype=float).reshape(-1, 4))
        self._vehicles()

    def _latch(self, name: str, msg) -> None:
        self._latched[name] = msg
        self._log(name, msg)

    def resend_latched(self) -> None:
        """Log the map and the current goal again. A Foxglove server forwards a message only to
        the clients subscribed at that moment, and both are sent once (the map at start, the
        goal once per episode), so the node calls this periodically for clients that join later."""
        for name, msg in self._latched.items():
            self._log(name, msg)

    def on_road(self, lanes: Sequence[tuple]) -> None:
        self._latch(CH_ROAD, road_update(lanes))

    def on_reference(self, x_imr, stamp_ns: int) -> None:
        self._log(CH_REFERENCE, reference_update(x_imr, stamp_ns, self.style))
        self._log(CH_REFERENCE_STATE, state_json(x_imr, stamp_ns))
        self._log(CH_TF, fm.FrameTransforms(transforms=[transform(FRAME_REFERENCE, x_imr, stamp_ns)]))

    def on_goal(self, goal, stamp_ns: int) -> None:
        self._latch(CH_GOAL, goal_update(goal, stamp_ns, self.style))

    def on_route(self, points, stamp_ns: int) -> None:
        self._log(CH_ROUTE, route_update(points, stamp_ns, self.style))

    def on_command(self, u, horizon, stamp_ns: int) -> None:
        self._log(CH_COMMAND, command_json(u, horizon, stamp_ns))

    def on_result(self, values: Mapping[str, str], stamp_ns: int, source: str = SOURCE_WORLD,
                  episode_return: Optional[float] = None) -> None:
        self._log(CH_EPISODE, episode_json(values, stamp_ns, source, episode_return))
