"""Road maps: parametric YAML -> lane-centreline graph, SV paths, conflict zones, A*.

A map file describes the road with a handful of numbers (lane width, lanes, kerb radius,
arm length, allowed turns); everything else (lane polylines, junction connectors, the
lane graph with lane-change edges, SV paths with their lookup grids and speed caps,
pairwise conflict zones, potential collision points) is derived here once per map and
cached, so a World reset costs nothing geometric.
"""
from __future__ import annotations

import functools
import heapq
import math
import pathlib
from dataclasses import dataclass, field

import numpy as np
import yaml

from bimacppo_common.conventions import TASKS

from .geometry import MapFrame, Path, bezier_connector, point_segment_distances, polyline_crossings

MAP_DIR = pathlib.Path(__file__).resolve().parent / "maps"
DEFAULT_MAP = "dual_lane_4way"
"""The map a tool draws or runs on when none is named."""
ARMS = {"north": (0.0, 1.0), "south": (0.0, -1.0), "east": (1.0, 0.0), "west": (-1.0, 0.0)}


def available_maps():
    return sorted(p.stem for p in MAP_DIR.glob("*.yaml"))


@dataclass
class Lane:
    """A lane centreline. kind: 'in' (towards the junction), 'out', 'conn' (inside the
    junction) or 'road' (straight map). index 0 = leftmost lane in driving direction."""
    id: str
    kind: str
    arm: str | None
    index: int
    points: np.ndarray
    heading: float
    length: float
    left: str | None = None
    right: str | None = None
    successors: list = field(default_factory=list)   # (lane id, via connector id or None)
    maneuver: str | None = None


@dataclass
class SVRoute:
    """A full SV path (in-lane + connector + out-lane) with its precomputed lookups."""
    key: tuple               # (arm, maneuver, in_index, out_index)
    path: Path
    s_entry: float           # arc length where the junction starts
    s_exit: float            # arc length where the junction ends
    in_lane: str
    out_lane: str
    connector: str | None
    conflicts: dict = field(default_factory=dict)   # other route key -> (a, b) on this path


def _bad(where, msg):
    raise ValueError(f"map {where}: {msg}")


def _num(d, key, where, lo=None, hi=None, integer=False):
    if key not in d:
        _bad(where, f"missing key '{key}'")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (integer and not isinstance(v, int)):
        _bad(where, f"key '{key}' must be {'an integer' if integer else 'a number'}, got {v!r}")
    if not math.isfinite(v) or (lo is not None and v < lo) or (hi is not None and v > hi):
        _bad(where, f"key '{key}' = {v} out of range [{lo}, {hi}]")
    return v


FOUR_WAY_KEYS = {"id", "type", "lane_width", "lanes_per_direction", "corner_radius", "arm_length",
                 "ev_arm", "sv_arms", "max_sv", "turns", "pose"}
STRAIGHT_KEYS = {"id", "type", "lane_width", "lanes", "length", "goal_ahead", "sv_ahead_min",
                 "sv_ahead_max", "max_sv", "pose"}
MAX_POSE_OFFSET_M = 5000.0
"""|pose.x|, |pose.y| bound: the map must fit inside the states receivers accept (1e4 m)."""


def _pose(spec, where) -> MapFrame:
    """Optional key ``pose: {x, y, heading}``: where the map's own frame sits in the fixed
    ``map`` frame (default: at its origin)."""
    if "pose" not in spec:
        return MapFrame()
    pose = spec["pose"]
    if not isinstance(pose, dict) or set(pose) - {"x", "y", "heading"}:
        _bad(where, "key 'pose' must be a mapping with keys x, y (m), heading (rad)")
    return MapFrame(_num(pose, "x", where, -MAX_POSE_OFFSET_M, MAX_POSE_OFFSET_M) if "x" in pose else 0.0,
                    _num(pose, "y", where, -MAX_POSE_OFFSET_M, MAX_POSE_OFFSET_M) if "y" in pose else 0.0,
                    _num(pose, "heading", where, -math.pi, math.pi) if "heading" in pose else 0.0)


class RoadMap:
    """Geometry and topology of one map; see module docstring. Build with load_map()."""

    def __init__(self, spec: dict, where: str, world_cfg=None):
        from .config import WorldConfig
        self.cfg = world_cfg or WorldConfig.load()
        if not isinstance(spec, dict):
            _bad(where, "top level must be a mapping")
        kind = spec.get("type")
        if kind not in ("four_way", "straight"):
            _bad(where, f"key 'type' must be 'four_way' or 'straight', got {kind!r}")
        allowed = FOUR_WAY_KEYS if kind == "four_way" else STRAIGHT_KEYS
        unknown = set(spec) - allowed
        if unknown:
            _bad(where, f"unknown key(s) {sorted(unknown)}")
        if not isinstance(spec.get("id"), str):
            _bad(where, "key 'id' must be a string")
        self.id = spec["id"]
        self.kind = kind
        self.frame = _pose(spec, where)   # everything below is built in the map's own frame
        self.lane_width = _num(spec, "lane_width", where, 2.0, 6.0)
        self.max_sv = _num(spec, "max_sv", where, 0, 16, integer=True)
        self.lanes: dict[str, Lane] = {}
        self.sv_routes: dict[tuple, SVRoute] = {}
        if kind == "four_way":
            self._build_four_way(spec, where)
        else:
            self._build_straight(spec, where)
        self._build_sv_routes()

    # ------------------------------------------------------------------ construction
    def _build_four_way(self, spec, where):
        W = self.lane_width
        self.n_lanes = n = _num(spec, "lanes_per_direction", where, 1, 4, integer=True)
        self.corner_radius = rc = _num(spec, "corner_radius", where, 0.0, 50.0)
        self.arm_length = A = _num(spec, "arm_length", where, 10.0, 1000.0)
        self.half_road = hw = n * W
        self.H = H = hw + rc
        ev_arm = spec.get("ev_arm")
        if ev_arm not in ARMS:
            _bad(where, f"key 'ev_arm' must be one of {list(ARMS)}, got {ev_arm!r}")
        sv_arms = spec.get("sv_arms")
        if not isinstance(sv_arms, list) or not sv_arms or any(a not in ARMS or a == ev_arm for a in sv_arms) \
                or len(set(sv_arms)) != len(sv_arms):
            _bad(where, f"key 'sv_arms' must be a list of distinct arms {list(ARMS)} other than ev_arm")
        self.ev_arm, self.sv_arms = ev_arm, list(sv_arms)
        if self.max_sv > len(sv_arms):
            _bad(where, f"max_sv = {self.max_sv} exceeds the number of SV arms ({len(sv_arms)}): one SV per arm")
        turns = spec.get("turns")
        if not isinstance(turns, dict) or set(turns) != set(TASKS):
            _bad(where, f"key 'turns' must map exactly {TASKS} to lists of [in, out] lane pairs")
        self.turns = {}
        for m, pairs in turns.items():
            if not isinstance(pairs, list) or not pairs:
                _bad(where, f"turns.{m} must be a non-empty list of [in, out] pairs")
            for pr in pairs:
                if not (isinstance(pr, list) and len(pr) == 2 and all(isinstance(i, int) and 0 <= i < n for i in pr)):
                    _bad(where, f"turns.{m}: bad pair {pr!r} (lane indices 0..{n - 1})")
            self.turns[m] = [tuple(p) for p in pairs]
        for arm, (dx, dy) in ARMS.items():
            d = np.array([dx, dy])
            hin = -d
            rin = np.array([hin[1], -hin[0]])
            rout = np.array([d[1], -d[0]])
            for k in range(n):
                o = (k + 0.5) * W * rin
                pts = np.array([d * (H + A) + o, d * H + o])
                self._add(Lane(f"{arm}_in_{k}", "in", arm, k, pts, math.atan2(hin[1], hin[0]), A))
                o = (k + 0.5) * W * rout
                pts = np.array([d * H + o, d * (H + A) + o])
                self._add(Lane(f"{arm}_out_{k}", "out", arm, k, pts, math.atan2(d[1], d[0]), A))
            for k in range(n):
                for kind in ("in", "out"):
                    ln = self.lanes[f"{arm}_{kind}_{k}"]
                    ln.left = f"{arm}_{kind}_{k - 1}" if k > 0 else None
                    ln.right = f"{arm}_{kind}_{k + 1}" if k < n - 1 else None
        for arm in ARMS:
            for m in TASKS:
                tgt = self.exit_arm(arm, m)
                for (i, j) in self.turns[m]:
                    a, b = self.lanes[f"{arm}_in_{i}"], self.lanes[f"{tgt}_out_{j}"]
                    pts = bezier_connector(a.points[-1], a.heading, b.points[0], b.heading)
                    cid = f"{arm}_in_{i}>{tgt}_out_{j}"
                    c = Lane(cid, "conn", None, -1, pts, a.heading, float(np.sum(np.hypot(*np.diff(pts, axis=0).T))),
                             maneuver=m)
                    self._add(c)
                    a.successors.append((b.id, cid))

    def _build_straight(self, spec, where):
        W = self.lane_width
        self.n_lanes = n = _num(spec, "lanes", where, 1, 8, integer=True)
        self.length = L = _num(spec, "length", where, 20.0, 5000.0)
        self.goal_ahead = _num(spec, "goal_ahead", where, 1.0, L)
        self.sv_ahead_min = _num(spec, "sv_ahead_min", where, 0.0, L)
        self.sv_ahead_max = _num(spec, "sv_ahead_max", where, self.sv_ahead_min, L)
        if self.max_sv > n:
            _bad(where, f"max_sv = {self.max_sv} exceeds lanes ({n}): one SV per lane")
        self.half_road = hw = n * W / 2.0
        self.ev_arm, self.sv_arms, self.turns = "south", [], {"straight": [(k, k) for k in range(n)]}
        for k in range(n):
            x = -hw + (k + 0.5) * W
            self._add(Lane(f"road_{k}", "road", None, k, np.array([[x, -L / 2], [x, L / 2]]), math.pi / 2, L,
                           left=f"road_{k - 1}" if k > 0 else None, right=f"road_{k + 1}" if k < n - 1 else None))

    def _add(self, lane):
        self.lanes[lane.id] = lane

    def exit_arm(self, arm: str, maneuver: str) -> str:
        """Arm reached from ``arm`` by a left/straight/right manoeuvre (right-hand traffic)."""
        dx, dy = ARMS[arm]
        hx, hy = -dx, -dy
        out = {"straight": (hx, hy), "left": (-hy, hx), "right": (hy, -hx)}[maneuver]
        for name, v in ARMS.items():
            if abs(v[0] - out[0]) < 1e-9 and abs(v[1] - out[1]) < 1e-9:
                return name
        raise AssertionError("unreachable")

    def _build_sv_routes(self):
        sc = self.cfg.sv
        if self.kind == "four_way":
            for arm in self.sv_arms + [self.ev_arm]:
                for m in TASKS:
                    for (i, j) in self.turns[m]:
                        a = self.lanes[f"{arm}_in_{i}"]
                        b = self.lanes[f"{self.exit_arm(arm, m)}_out_{j}"]
                        cid = f"{a.id}>{b.id}"
                        c = self.lanes[cid]
                        pts = np.vstack([a.points[:-1], c.points, b.points[1:]])
                        r = SVRoute((arm, m, i, j), Path(pts, sc.path_sample), a.length, a.length + c.length,
                                    a.id, b.id, cid)
                        self.sv_routes[r.key] = r
        else:
            for k in range(self.n_lanes):
                ln = self.lanes[f"road_{k}"]
                r = SVRoute(("road", "straight", k, k), Path(ln.points, sc.path_sample), ln.length, ln.length,
                            ln.id, ln.id, None)
                self.sv_routes[r.key] = r
        for r in self.sv_routes.values():
            r.path.build_grid(sc.grid_cell, sc.grid_radius)
            r.path.build_speed_cap(sc.lateral_accel_max)
        keys = list(self.sv_routes)
        for ka in keys:
            for kb in keys:
                if ka[0] != kb[0]:
                    z = self._conflict_zone(self.sv_routes[ka], self.sv_routes[kb])
                    if z is not None:
                        self.sv_routes[ka].conflicts[kb] = z

    def _conflict_zone(self, ra: SVRoute, rb: SVRoute):
        """Arc-length interval of ``ra`` in which the two bodies could overlap: the centre
        of ``ra`` is closer to ``rb``'s centreline than hw + hl|sin d| + hw|cos d| + margin
        (d = relative heading; so adjacent parallel lanes do not conflict, crossings do).
        Only the junction part is scanned; merge zones end conflict_cap_after_exit past
        the junction exit, where IDM car following takes over."""
        sc, veh = self.cfg.sv, self.cfg.vehicle
        hl, hw = 0.5 * veh.length, 0.5 * veh.width
        reach = hl + hw + sc.conflict_margin
        cap = sc.conflict_cap_after_exit

        def window(r):
            lo = max(0.0, r.s_entry - reach - 1.0)
            hi = min(r.path.length, r.s_exit + cap)
            i0, i1 = int(lo * r.path.inv_ds), int(hi * r.path.inv_ds) + 1
            return i0, r.path.points()[i0:i1], np.asarray(r.path.psis[i0:i1])
        i0, A, psiA = window(ra)
        _, B, _ = window(rb)
        if len(A) < 2 or len(B) < 2:
            return None
        dist, seg = point_segment_distances(A, B, return_segment=True)
        dB = np.diff(B, axis=0)[seg]
        rel = psiA - np.arctan2(dB[:, 1], dB[:, 0])
        thr = hw + hl * np.abs(np.sin(rel)) + hw * np.abs(np.cos(rel)) + sc.conflict_margin
        idx = np.nonzero(dist < thr)[0]
        if len(idx) == 0:
            return None
        return ((i0 + idx[0]) * ra.path.ds, (i0 + idx[-1]) * ra.path.ds)

    # ------------------------------------------------------------------ queries
    #: speed floor (m/s) of ``time_to_box``: a vehicle standing or crawling next to the box
    #: counts as arriving soon, not never
    BOX_SPEED_FLOOR = 0.5

    def box_gap(self, x: float, y: float) -> float:
        """Distance (m) from (x, y) to the junction box |x|, |y| <= H of the map frame, measured
        along the arm it lies on (max(|x|, |y|) - H); <= 0 inside the box, +inf on a map without
        a junction."""
        if self.kind != "four_way":
            return math.inf
        return max(abs(x), abs(y)) - self.H

    def time_to_box(self, x: float, y: float, v: float, psi: float) -> float:
        """Seconds until a vehicle at (x, y), speed v, heading psi reaches the junction box at
        its speed (floored at ``BOX_SPEED_FLOOR``): 0 inside the box, +inf when it heads away
        from the junction centre or the map has no junction. The one rule behind the "yield"
        driver's threat test (``drivers.junction_threatened``) and the planner's junction
        features (``decision.observe``)."""
        d = self.box_gap(x, y)
        if d <= 0.0:
            return 0.0
        if not math.isfinite(d) or math.cos(psi) * (-x) + math.sin(psi) * (-y) <= 0.0:
            return math.inf
        return d / max(v, self.BOX_SPEED_FLOOR)

    def drivable(self, x: float, y: float) -> bool:
        """True when (x, y) lies on the paved area (lanes, junction box minus kerb fillets)."""
        ax, ay = abs(x), abs(y)
        hw = self.half_road
        if self.kind == "straight":
            return ax <= hw and ay <= 0.5 * self.length
        H, ext = self.H, self.H + self.arm_length
        if ax <= hw:
            return ay <= ext
        if ay <= hw:
            return ax <= ext
        if ax <= H and ay <= H:
            dx, dy = H - ax, H - ay
            return dx * dx + dy * dy >= self.corner_radius * self.corner_radius
        return False

    def locate(self, x: float, y: float):
        """(lane id, arc length along it) of the straight lane containing (x, y), or None
        inside the junction / off the road."""
        W = self.lane_width
        if self.kind == "straight":
            k = int(math.floor((x + self.half_road) / W))
            if 0 <= k < self.n_lanes and abs(y) <= 0.5 * self.length:
                return f"road_{k}", y + 0.5 * self.length
            return None
        H, hw = self.H, self.half_road
        for arm, (dx, dy) in ARMS.items():
            along = x * dx + y * dy
            if along < H:
                continue
            lat = x * (-dy) + y * dx          # along the incoming lane's right vector
            if abs(lat) > hw or along > H + self.arm_length:
                return None
            if lat >= 0:
                k = min(int(lat / W), self.n_lanes - 1)
                return f"{arm}_in_{k}", H + self.arm_length - along
            k = min(int(-lat / W), self.n_lanes - 1)
            return f"{arm}_out_{k}", along - H
        return None

    def lane_point(self, lane_id: str, s: float):
        """(x, y, heading) at arc length s on a straight lane."""
        ln = self.lanes[lane_id]
        p0, p1 = ln.points[0], ln.points[-1]
        t = s / ln.length
        return (float(p0[0] + t * (p1[0] - p0[0])), float(p0[1] + t * (p1[1] - p0[1])), ln.heading)

    def lateral_point(self, x: float, y: float, psi: float, side: int):
        """Point on the adjacent same-direction lane (side -1 = left, +1 = right) at the
        same station as (x, y), as np.array([x, y, heading]); None if there is none
        (no such lane, inside the junction, off-road, or driving against the lane)."""
        if side not in (-1, 1):
            raise ValueError(f"side must be -1 (left) or +1 (right), got {side!r}")
        loc = self.locate(x, y)
        if loc is None:
            return None
        ln = self.lanes[loc[0]]
        if math.cos(psi - ln.heading) <= 0.0:
            return None
        nb = ln.left if side < 0 else ln.right
        if nb is None:
            return None
        return np.array(self.lane_point(nb, loc[1]))

    def lane_index(self, x: float, y: float):
        """(lane id, index) the point is on, or None inside the junction."""
        loc = self.locate(x, y)
        return None if loc is None else (loc[0], self.lanes[loc[0]].index)

    # ------------------------------------------------------------------ routing
    def plan_route(self, start_lane: str, s_start: float, goal_lane: str, s_goal: float,
                   no_lane_change_zone: float | None = None):
        """A* over the lane graph (stations every graph_step m; lane-change edges of
        lane_change_length m between adjacent same-direction lanes; junction connectors).
        Returns the route polyline (K, 2) from the start point to the goal point.
        ``no_lane_change_zone`` overrides the configured one (a late re-plan may need 0)."""
        cfg = self.cfg
        zone = cfg.no_lane_change_zone if no_lane_change_zone is None else float(no_lane_change_zone)
        for lid in (start_lane, goal_lane):
            if lid not in self.lanes or self.lanes[lid].kind == "conn":
                raise ValueError(f"route endpoints must be straight lanes, got {lid!r}")

        def stations(lid):
            ln = self.lanes[lid]
            m = max(1, int(math.ceil(ln.length / cfg.graph_step)))
            return m, ln.length / m

        def pos(node):
            lid, k = node
            m, st = stations(lid)
            x, y, _ = self.lane_point(lid, k * st)
            return x, y

        m0, st0 = stations(start_lane)
        k0 = min(m0, int(math.ceil(s_start / st0 - 1e-9)))
        mg, stg = stations(goal_lane)
        kg = min(mg, int(math.floor(s_goal / stg + 1e-9)))
        start, goal = (start_lane, k0), (goal_lane, kg)
        gx, gy = pos(goal)

        def h(node):
            x, y = pos(node)
            return math.hypot(x - gx, y - gy)

        W = self.lane_width
        counter = 0
        openq = [(h(start), 0, 0.0, start)]
        came = {start: (None, None)}
        cost = {start: 0.0}
        while openq:
            _, _, g, node = heapq.heappop(openq)
            if node == goal:
                break
            if g > cost[node] + 1e-9:
                continue
            lid, k = node
            ln = self.lanes[lid]
            m, st = stations(lid)
            nbrs = []
            if k < m:
                nbrs.append(((lid, k + 1), st, None))
            else:
                for nxt, via in ln.successors:
                    nbrs.append(((nxt, 0), self.lanes[via].length, via))
            dk = max(1, int(round(cfg.lane_change_length / st)))
            s_here = k * st
            lc_ok = k + dk <= m and (ln.kind == "out" or ln.kind == "road" or
                                     (ln.kind == "in" and (k + dk) * st <= ln.length - zone))
            if lc_ok:
                for nb in (ln.left, ln.right):
                    if nb is not None:
                        # tiny tie-breaker: earlier lane changes are preferred
                        c = math.hypot(dk * st, W) + cfg.lane_change_penalty + 1e-6 * s_here
                        nbrs.append(((nb, k + dk), c, "lc"))
            for nxt, c, via in nbrs:
                ng = g + c
                if ng < cost.get(nxt, math.inf) - 1e-12:
                    cost[nxt] = ng
                    came[nxt] = (node, via)
                    counter += 1
                    heapq.heappush(openq, (ng + h(nxt), counter, ng, nxt))
        if goal not in came:
            raise ValueError(f"no route from {start_lane} to {goal_lane} on map {self.id}")
        seq = []
        node = goal
        while node is not None:
            prev, via = came[node]
            seq.append((node, via))
            node = prev
        seq.reverse()
        pts = [self.lane_point(start_lane, s_start)[:2]]
        for node, via in seq:
            if via is not None and via != "lc":
                pts.extend(map(tuple, self.lanes[via].points[1:-1]))
            p = pos(node)
            if math.hypot(p[0] - pts[-1][0], p[1] - pts[-1][1]) > 1e-6:
                pts.append(p)
        pts.append(self.lane_point(goal_lane, s_goal)[:2])
        return np.array(pts), [via for _, via in seq if via not in (None, "lc")], \
            sum(1 for _, via in seq if via == "lc")

    # ------------------------------------------------------------------ conflict points
    def ev_connector(self, in_index: int, task: str) -> str:
        """Junction connector the EV uses for ``task`` when it enters from in-lane ``in_index``."""
        pairs = self.turns[task]
        pair = next((p for p in pairs if p[0] == in_index), pairs[0])
        return f"{self.ev_arm}_in_{pair[0]}>{self.exit_arm(self.ev_arm, task)}_out_{pair[1]}"

    def connector_conflicts(self, ca: str, cb: str) -> int:
        """Potential collision points of two junction connectors: proper crossings of the
        centrelines, plus one merge point when both end in the same lane, plus one
        diverge point when both start in the same lane (paper Fig. 3)."""
        key = (ca, cb)
        cache = self.__dict__.setdefault("_pcp_cache", {})
        if key in cache:
            return cache[key]
        a, b = self.lanes[ca], self.lanes[cb]
        n = len(polyline_crossings(a.points, b.points))
        a_in, a_out = ca.split(">")
        b_in, b_out = cb.split(">")
        cache[key] = n + (a_out == b_out) + (a_in == b_in)
        return cache[key]

    def pcp_count(self, task: str, sv_arm: str, ev_in_index: int | None = None, sv_maneuver: str | None = None):
        """N_pcp between the EV doing ``task`` and one SV from ``sv_arm``: summed over the
        SV's possible manoeuvres (and their lane pairs) unless ``sv_maneuver`` is given."""
        if self.kind != "four_way":
            return 0
        if task not in TASKS:
            raise ValueError(f"unknown task {task!r}; expected one of {TASKS}")
        if sv_arm not in ARMS or sv_arm == self.ev_arm:
            raise ValueError(f"bad SV arm {sv_arm!r}")
        ev_in = self.turns[task][0][0] if ev_in_index is None else ev_in_index
        ce = self.ev_connector(ev_in, task)
        total = 0
        for m in ([sv_maneuver] if sv_maneuver else TASKS):
            for (i, j) in self.turns[m]:
                total += self.connector_conflicts(ce, f"{sv_arm}_in_{i}>{self.exit_arm(sv_arm, m)}_out_{j}")
        return total

    @property
    def tasks(self) -> tuple:
        """The tasks the map offers, in TASKS order (a straight road: "straight" only)."""
        return tuple(t for t in TASKS if t in self.turns)

    def infer_n_pcp(self, ev_start_xy, goal_xy, sv_tracks) -> int | None:
        """N_pcp of an episode from what a receiver of the states sees (map frame of this
        road): the EV's connector from its lane at the start (``ev_start_xy``) and the task
        the goal's lane implies; each SV's connector from the in-lane it was first seen in
        and the out-lane it was last seen in (``sv_tracks``: (first_xy, last_xy) per SV).
        An SV not yet seen on an out-lane counts its allowed connector with the fewest
        points (a lower bound); an SV first seen elsewhere than on an SV arm's in-lane
        counts 0. None if the goal is on no exit lane of the EV's arm (no task to infer)."""
        if self.kind != "four_way":
            return 0
        goal = self.locate(float(goal_xy[0]), float(goal_xy[1]))
        goal_lane = self.lanes[goal[0]] if goal is not None else None
        task = next((m for m in TASKS if goal_lane is not None and goal_lane.kind == "out"
                     and self.exit_arm(self.ev_arm, m) == goal_lane.arm), None)
        if task is None:
            return None
        start = self.locate(float(ev_start_xy[0]), float(ev_start_xy[1]))
        start_lane = self.lanes[start[0]] if start is not None else None
        ev_in = start_lane.index if start_lane is not None and start_lane.kind == "in" and \
            start_lane.arm == self.ev_arm else self.turns[task][0][0]
        ce = self.ev_connector(ev_in, task)
        total = 0
        for first_xy, last_xy in sv_tracks:
            f = self.locate(float(first_xy[0]), float(first_xy[1]))
            fl = self.lanes[f[0]] if f is not None else None
            if fl is None or fl.kind != "in" or fl.arm == self.ev_arm:
                continue
            options = [f"{fl.id}>{self.exit_arm(fl.arm, m)}_out_{j}" for m in TASKS
                       for (i, j) in self.turns[m] if i == fl.index]
            last = self.locate(float(last_xy[0]), float(last_xy[1]))
            known = [c for c in options if last is not None and c.endswith(">" + last[0])]
            counts = [self.connector_conflicts(ce, c) for c in (known or options)]
            total += counts[0] if known else min(counts, default=0)
        return total


def map_from_yaml(text: str, where: str) -> RoadMap:
    """A map from the text of a map file (``where`` names it in errors): how a map that travels
    with a recording is read back where its file does not exist."""
    try:
        spec = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"map {where}: not valid YAML: {exc}") from None
    return RoadMap(spec, where)


@functools.lru_cache(maxsize=16)
def _load_cached(path: str) -> RoadMap:
    with open(path) as fh:
        return map_from_yaml(fh.read(), path)


def load_map(id_or_path: str | pathlib.Path) -> RoadMap:
    """Load a map by id (``dual_lane_4way``, ``single_lane_4way``, ``three_lane_straight``)
    or from a YAML path. Maps are cached (they are immutable after construction)."""
    p = pathlib.Path(id_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        if not p.is_file():
            raise ValueError(f"map file not found: {p}")
        return _load_cached(str(p.resolve()))
    if str(id_or_path) not in available_maps():
        raise ValueError(f"unknown map id {str(id_or_path)!r}; available: {available_maps()}")
    return _load_cached(str(MAP_DIR / f"{id_or_path}.yaml"))
