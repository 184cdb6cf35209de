"""The RL agent's view of the world: observation (eq. 18-20) and action decoding (§III-C).

Both the Gymnasium environment (training, in-process evaluation) and the ROS planner
node use this module on plain arrays, so an observation computed from ROS messages is
bit-identical to the one computed in-process. Nothing here knows about the simulator's
internals: it needs the EV state, the SV states, the goal pose, the A* waypoint set and
the road's `lateral_point` (for the lane-change sub-action).
"""
from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from bimacppo_common import config
from bimacppo_common.conventions import wrap_angle
from bimacppo_common.config import ConfigError, Packaged, config_class, invalid, setting  # noqa: F401  (ConfigError: re-exported)

TIMEOUT_MODES = ("terminal", "truncate")
ZERO_SPEED_MODES = ("waypoint", "hold")


# Every default is written once, in config/env.yaml; a variant file or dict overlays it
# (bimacppo_common.config states the rules).
ENV_YAML = Packaged("bimacppo_planner", "config/env.yaml")


@config_class(ENV_YAML, "observation")
class ObservationConfig:
    max_sv: int = setting(lo=0, hi=16)
    sv_clip: float = setting(lo=0.0, lo_open=True)
    sv_order: str = setting(choices=("distance", "id"))
    pad_value: tuple[float, ...] = setting(length=4)
    sv_frame: str = setting(choices=("paper", "ego"))   # paper: |dx|, |dy| in the map frame (eq. 20); ego: signed, in the EV's frame
    junction: bool = setting(absent=False)   # append the junction features (extension, docs/method.md); false: eq. (18)-(20) only
    tta_cap: float = setting(lo=0.0, lo_open=True)   # s; the junction features' time-to-box ceiling ("not coming")
    lanes: bool = setting(absent=False)      # append the lane features (extension, docs/method.md)
    leads: bool = setting(absent=False)      # append the lead features (extension, docs/method.md)


#: what the chord limit tests: the chord's distance from the route points, or that a corridor
#: around the chord lies on the paved road (decode_action)
CHORD_RULES = ("route", "road")
#: spacing (m) of the points at which the "road" chord rule tests the corridor; well under the
#: kerb radius of any map, so no corner fillet fits between two tests
CHORD_STEP = 0.5
#: which lane A3 counts from: the route's, the one the EV is in, or the one the episode's decisions
#: have chosen so far (decode_action)
LANE_CHANGE_FROM = ("route", "ev", "chosen")
#: what action.lane_change_commit holds while a lane change is under way: every further change,
#: or only one back towards the side the EV comes from (decode_action)
COMMIT_HOLDS = ("all", "reversals")
#: with action.reach_time, a waypoint this many times its lateral offset from the EV ahead stays
#: allowed whatever the speed: the approach to it is then at most atan(1/3) = 18 deg off the
#: road's heading, a lane change the NMPC completes without leaving the road (decode_action)
REACH_PER_LATERAL = 3.0


@config_class(ENV_YAML, "action")
class ActionConfig:
    n_waypoints: int = setting(lo=1)
    speeds: tuple[float, ...] = setting(lo=0.0, min_length=1)
    lane_change: tuple[int, ...]
    decision_every: int = setting(lo=1)
    zero_speed: str = setting(choices=ZERO_SPEED_MODES)   # waypoint (paper) | hold: see env.yaml
    hold_decel: float | None = setting(lo=0.0, lo_open=True, absent=None)   # m/s^2; where a hold stops, see env.yaml
    chord_tol: float | None = setting(lo=0.0, lo_open=True)   # m; None: off (the paper), see env.yaml
    chord_rule: str = setting(choices=CHORD_RULES, absent="route")   # what the chord limit tests, see env.yaml
    min_lookahead: float | None = setting(lo=0.0, lo_open=True)   # m; None: off (the paper), see env.yaml
    lane_change_from: str = setting(choices=LANE_CHANGE_FROM, absent="route")   # the lane A3 counts from, see env.yaml
    reach_time: float | None = setting(lo=0.0, lo_open=True, absent=None)   # s; None: off (the paper), see env.yaml
    lane_change_commit: float | None = setting(lo=0.0, lo_open=True, absent=None)   # m; None: off (the paper), see env.yaml
    lane_change_commit_holds: str = setting(choices=COMMIT_HOLDS, absent="all")   # what the commitment holds, see env.yaml

    def _check(self) -> None:
        if self.lane_change != (-1, 0, 1):
            raise invalid("lane_change", f"must be [-1, 0, 1] (left, keep, right), got {list(self.lane_change)}")
        if self.lane_change_commit is not None and self.lane_change_from != "chosen":
            raise invalid("lane_change_commit", f"needs lane_change_from: chosen, got {self.lane_change_from!r}")


@config_class(ENV_YAML, "reward")
class RewardConfig:
    success_base: float
    alpha1: float
    alpha2: float
    alpha3: float
    r_f_max: float
    collision_base: float = setting(hi=0.0)   # penalties: <= 0
    alpha4: float = setting(hi=0.0)
    timeout: float
    timeout_mode: str = setting(choices=TIMEOUT_MODES)
    threat_entry: float = setting(hi=0.0)
    idle_clear: float = setting(hi=0.0)
    threat_speed: float = setting(hi=0.0)
    headway: float = setting(hi=0.0, absent=0.0)
    free_lane: float = setting(hi=0.0, absent=0.0)
    idle_speed: float = setting(lo=0.0)
    go_speed: float = setting(lo=0.0)
    idle_queue_gap: float | None = setting(lo=0.0, lo_open=True, absent=None)   # m; None: off, see env.yaml
    lane_change: float
    step: float

    @property
    def timeout_terminal(self) -> bool:
        """Whether a timeout ends the MDP (no bootstrap) rather than truncating it."""
        return self.timeout_mode == "terminal"


@config_class(ENV_YAML)
class EnvConfig:
    observation: ObservationConfig
    action: ActionConfig
    reward: RewardConfig

    @classmethod
    def load(cls, path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> "EnvConfig":
        """The packaged ``config/env.yaml``, overlaid by the YAML at ``path`` (a variant lists only
        what it changes), then by ``overrides`` ({"reward.step": -0.1} or nested dicts)."""
        return config.load(cls, path, overrides)

    @classmethod
    def from_dict(cls, raw: Mapping[str, Any], where: str = "<dict>") -> "EnvConfig":
        """A dict in env.yaml's layout (a policy's saved ``to_dict()``, or a few keys) over the defaults."""
        return config.from_dict(cls, raw, where)

    def to_dict(self) -> dict:
        return config.to_dict(self)

    @property
    def obs_dim(self) -> int:
        return sum(size for _, size in observation_blocks(self.observation))

    @property
    def nvec(self) -> tuple[int, int, int]:
        return (self.action.n_waypoints, len(self.action.speeds), len(self.action.lane_change))


#: where A3, the lane-change head, sits in an action (the order of EnvConfig.nvec: A1, A2, A3)
LANE_CHANGE_HEAD = 2

#: the lane features: same-direction lanes to the EV's left, then to its right
LANE_FEATURES = 2
#: the lanes the lead features describe, counted from the EV's lane: left, its own, right
LEAD_LANES = (-1, 0, 1)
#: per lane: gap to the nearest SV ahead, the EV's closing speed on it, gap to the nearest SV behind
LEAD_FEATURES = 3 * len(LEAD_LANES)


def observation_blocks(cfg: ObservationConfig) -> tuple[tuple[str, int], ...]:
    """The observation's feature groups in their order, with their sizes: eq. (18)-(20)
    ("paper"), then the optional extensions. A fine-tune that turns a group on widens the
    checkpoint's input layer by it (``bimacppo_learning.trainer.widen_observation``), which needs
    each group to keep its place and size whatever else is on."""
    blocks = [("paper", 4 * (1 + cfg.max_sv))]
    if cfg.junction:
        blocks.append(("junction", 1 + cfg.max_sv))
    if cfg.lanes:
        blocks.append(("lanes", LANE_FEATURES))
    if cfg.leads:
        blocks.append(("leads", LEAD_FEATURES))
    return tuple(blocks)


def lanes_beside(road, x: float, y: float, psi: float) -> tuple[int, int]:
    """(lanes to the left, lanes to the right) of the lane the EV at (x, y, psi) is in, counted
    on the planner's own map with the walk A3 decodes by (``lanes_across``): (0, 0) inside a
    junction, off the road or against the lane's direction."""
    lanes = lanes_across(road.lateral_point, x, y, psi)
    return sum(1 for n in lanes if n < 0), sum(1 for n in lanes if n > 0)


def lane_leads(road, ego, svs: np.ndarray, clip: float) -> np.ndarray:
    """The lead features: for each lane of ``LEAD_LANES`` (left of the EV's, its own, right of
    it, found on the planner's map by the walk A3 decodes with, ``lanes_across``), the distance
    along the EV's heading to the nearest same-direction SV ahead in that lane (centre to centre,
    at most ``clip``; ``clip`` when there is none), the EV's speed less that SV's speed along the
    EV's heading (0 when there is none), and the distance to the nearest such SV behind (at most
    ``clip``). An SV is in a lane when its offset across the EV's heading lies within half a lane
    width of the lane's centre, the EV's own lane centred on the EV. A lane that is not there
    (the road's edge, inside a junction, against the lane's direction) reads 0, 0, 0: no room
    ahead or behind."""
    x, y, v, psi = (float(ego[0]), float(ego[1]), float(ego[2]), float(ego[3]))
    lanes = lanes_across(road.lateral_point, x, y, psi)
    half = 0.5 * float(road.lane_width)
    c, s = math.cos(psi), math.sin(psi)
    out = np.zeros(LEAD_FEATURES, dtype=np.float64)
    for k, n in enumerate(LEAD_LANES):
        if n not in lanes:
            continue
        offset = lanes[n][3]           # 0 for the EV's own lane: lanes_across starts at the EV
        ahead, closing, behind = clip, 0.0, clip
        for sx, sy, sv, spsi in svs:
            along = math.cos(float(spsi) - psi)
            if along <= 0.0:
                continue
            dx = c * (sx - x) + s * (sy - y)
            dy = -s * (sx - x) + c * (sy - y)
            if abs(dy - offset) >= half:
                continue
            if 0.0 <= dx < ahead:
                ahead, closing = dx, v - float(sv) * along
            elif dx < 0.0 and -dx < behind:
                behind = -dx
        out[3 * k:3 * k + 3] = (ahead, closing, behind)
    return out


def observe(cfg: ObservationConfig, ego: np.ndarray, goal: np.ndarray, svs: np.ndarray, road=None) -> np.ndarray:
    """Eq. (18)-(20): EV features relative to the goal, then one row per SV, padded to N_sv^max;
    with ``cfg.junction`` the junction features follow (``road``, a ``RoadMap`` in whose frame
    the states are given, is then required).

    SVs beyond N_sv^max are dropped farthest-first (the nearest ones matter for safety).

    Junction features (an extension, docs/method.md): the EV's distance to the junction box
    (``RoadMap.box_gap``, clipped to [-sv_clip, sv_clip]), then per SV slot, in the rows' order,
    its time to reach the box at its own speed (``RoadMap.time_to_box``, capped at ``tta_cap``;
    an empty slot reads ``tta_cap``). They are functions of the observed states and the
    planner's own map, the same rule the "yield" driver's threat test applies, so the policy
    sees what a threatened junction is instead of having to compose it from the goal offsets
    and the SV rows.

    Lane features (an extension, docs/method.md): the same-direction lanes to the EV's left and
    to its right (``lanes_beside``), from the planner's map. Without them a side with no SV looks
    the same whether it is a free lane or no lane at all, which is the choice A3 makes.

    Lead features (an extension, docs/method.md): ``lane_leads`` of all observed SVs (not only
    the N_sv^max nearest), clipped at ``sv_clip``. The SV rows say where each SV is; these say
    which lane it blocks, the question behind following, passing and a lane change's gap.
    """
    x, y, v, psi = (float(ego[0]), float(ego[1]), float(ego[2]), float(ego[3]))
    blocks = observation_blocks(cfg)
    starts = itertools.accumulate((size for _, size in blocks), initial=0)
    block_starts = dict(zip((name for name, _ in blocks), starts))
    out = np.empty(sum(size for _, size in blocks), dtype=np.float32)
    out[0] = abs(x - float(goal[0]))
    out[1] = abs(y - float(goal[1]))
    out[2] = v
    out[3] = wrap_angle(psi - float(goal[2]))
    svs = np.asarray(svs, dtype=np.float64).reshape(-1, 4)
    all_svs = svs
    if cfg.sv_order == "distance" and len(svs) > 1:
        order = np.argsort(np.hypot(svs[:, 0] - x, svs[:, 1] - y), kind="stable")
        svs = svs[order]
    c = cfg.sv_clip
    ego_frame = cfg.sv_frame == "ego"
    cp, sp = math.cos(psi), math.sin(psi)
    for k in range(cfg.max_sv):
        o = 4 + 4 * k
        if k < len(svs):
            sx, sy, sv, spsi = svs[k]
            if ego_frame:
                # an extension (docs/method.md): where the SV is relative to the EV, ahead/behind and
                # left/right kept, which eq. (20)'s absolute values discard
                dx, dy = sx - x, sy - y
                out[o] = min(max(cp * dx + sp * dy, -c), c)
                out[o + 1] = min(max(-sp * dx + cp * dy, -c), c)
            else:
                out[o] = min(abs(x - sx), c)
                out[o + 1] = min(abs(y - sy), c)
            out[o + 2] = v - sv
            out[o + 3] = wrap_angle(psi - spsi)
        else:
            out[o:o + 4] = cfg.pad_value
    if cfg.junction:
        if road is None:
            raise ValueError("observation.junction needs the road map (observe(..., road=...))")
        cap = cfg.tta_cap
        n_base = block_starts["junction"]
        out[n_base] = min(max(road.box_gap(x, y), -c), c)
        for k in range(cfg.max_sv):
            if k < len(svs):
                sx, sy, sv, spsi = svs[k]
                out[n_base + 1 + k] = min(road.time_to_box(sx, sy, sv, spsi), cap)
            else:
                out[n_base + 1 + k] = cap
    if cfg.lanes:
        if road is None:
            raise ValueError("observation.lanes needs the road map (observe(..., road=...))")
        at = block_starts["lanes"]
        out[at:at + LANE_FEATURES] = lanes_beside(road, x, y, psi)
    if cfg.leads:
        if road is None:
            raise ValueError("observation.leads needs the road map (observe(..., road=...))")
        at = block_starts["leads"]
        out[at:at + LEAD_FEATURES] = lane_leads(road, ego, all_svs, cfg.sv_clip)
    return out


class WaypointTracker:
    """Keeps the reference waypoint set of §III-C and offers A1.

    Waypoints behind the EV are removed (monotonically: a waypoint once passed never
    comes back, as in the paper); A1 is the next ``n`` of those left, WP0 nearest, which
    is what lets the policy stop or yield by choosing WP0. Near the goal, when fewer than
    ``n`` remain, the last waypoint is repeated so the action space keeps its size.

    With ``min_lookahead`` (m) A1 offers the next ``n`` waypoints that lie at least that far
    ahead of the EV (along each waypoint's heading, the test that removes passed ones), as a
    pure-pursuit tracker keeps a minimum look-ahead: the NMPC heads for x_IMR in a straight line,
    so a waypoint a few decimetres ahead but a metre or more to the side (the EV off the lane
    centre, or a lane change ordered while creeping) asks for a heading change of 60-80 degrees,
    and the EV drives off the road at the next waypoint. ``idx`` stays the nearest waypoint not
    yet passed; ``start`` is where A1's waypoints begin.
    """

    def __init__(self, route: np.ndarray, n: int, min_lookahead: float | None = None):
        route = np.asarray(route, dtype=np.float64)
        if route.ndim != 2 or route.shape[1] != 3 or len(route) == 0 or not np.all(np.isfinite(route)):
            raise ValueError(f"route must be a non-empty finite (M, 3) array of [x, y, psi], got shape {route.shape}")
        if min_lookahead is not None and not (math.isfinite(min_lookahead) and min_lookahead > 0.0):
            raise ValueError(f"min_lookahead must be a positive number of metres or None, got {min_lookahead!r}")
        self.route = route
        self.n = n
        self.min_lookahead = min_lookahead
        self.idx = 0
        self.start = 0
        self.lane = 0            # the lane A3 has chosen, in lanes beside the route (lane_change_from: chosen)
        self._cos = np.cos(route[:, 2])
        self._sin = np.sin(route[:, 2])

    @classmethod
    def for_action(cls, route: np.ndarray, cfg: ActionConfig) -> "WaypointTracker":
        """The tracker that ``decode_action(..., cfg)`` expects: A1's size and look-ahead from ``cfg``."""
        return cls(route, cfg.n_waypoints, cfg.min_lookahead)

    def _ahead(self, i: int, x: float, y: float) -> float:
        r = self.route
        return (r[i, 0] - x) * self._cos[i] + (r[i, 1] - y) * self._sin[i]

    def update(self, x: float, y: float) -> None:
        m = len(self.route) - 1
        i = self.idx
        while i < m and self._ahead(i, x, y) < 0.0:
            i += 1
        self.idx = i
        if self.min_lookahead is not None:
            while i < m and self._ahead(i, x, y) < self.min_lookahead:
                i += 1
        self.start = i

    def candidates(self) -> np.ndarray:
        j = np.minimum(np.arange(self.start, self.start + self.n), len(self.route) - 1)
        return self.route[j]

    def heading_here(self) -> float:
        """The route's heading at the nearest waypoint not yet passed (WP0 without a look-ahead)."""
        return float(self.route[self.idx, 2])

    def station(self, x: float, y: float) -> tuple[int, float, float]:
        """Where the EV is along the route: (x, y) projected onto the route segment that ends at
        the nearest waypoint not yet passed (clamped to it), as (that waypoint's index, px, py)."""
        r, i = self.route, self.idx
        a, b = r[max(i - 1, 0)], r[i]
        dx, dy = b[0] - a[0], b[1] - a[1]
        len2 = dx * dx + dy * dy
        t = 0.0 if len2 < 1e-18 else min(max(((x - a[0]) * dx + (y - a[1]) * dy) / len2, 0.0), 1.0)
        return i, float(a[0] + t * dx), float(a[1] + t * dy)

    def ahead(self, x: float, y: float, d: float) -> tuple[float, float, float]:
        """The point d metres further along the route than the EV at (x, y), kept at the EV's
        offset from the route: the EV's position moved by the route's own displacement from the
        EV's station over arc length d (so it bends with the route and keeps the lane the EV is
        in), and the route's heading there. Beyond the route's end it stays at the end."""
        r, m = self.route, len(self.route) - 1
        i, px, py = self.station(x, y)
        qx, qy, left = px, py, float(d)
        psi = float(r[i, 2])
        while left > 0.0:
            psi = float(r[i, 2])          # the heading of the segment being walked
            seg = math.hypot(r[i, 0] - qx, r[i, 1] - qy)
            if seg >= left:
                t = left / seg
                qx, qy = qx + t * (r[i, 0] - qx), qy + t * (r[i, 1] - qy)
                break
            left -= seg
            qx, qy = float(r[i, 0]), float(r[i, 1])
            if i == m:
                break
            i += 1
        return x + qx - px, y + qy - py, psi

    def ahead_of(self, k: int, x: float, y: float) -> float:
        """How far candidate WPk lies ahead of (x, y), along the route's heading at the waypoint."""
        return self._ahead(min(self.start + k, len(self.route) - 1), x, y)

    def reach_limited(self, k: int, x: float, y: float, reach: float) -> int:
        """The farthest of WP0..WPk that lies at most ``reach`` metres ahead of (x, y)
        (``ahead_of``). WP0 is always allowed: it is the nearest waypoint the decoding may aim at."""
        for kk in range(k, 0, -1):
            if self.ahead_of(kk, x, y) <= reach:
                return kk
        return 0

    def chord_limited(self, k: int, x: float, y: float, tol: float) -> int:
        """The farthest of WP0..WPk whose chord from (x, y) passes every route point before it
        within ``tol`` (m). The route is a polyline through its points, so checking its vertices
        bounds the whole path between the EV and the waypoint. WP0 is always allowed: without a
        look-ahead there is no route point between the EV and it, with one it is the nearest
        waypoint the decoding may aim at."""
        r, m = self.route, len(self.route) - 1

        def off_chord(i: int, dx: float, dy: float, len2: float) -> float:
            # distance of route point i from the segment EV -> (x + dx, y + dy)
            px, py = r[i, 0] - x, r[i, 1] - y
            t = min(max((px * dx + py * dy) / len2, 0.0), 1.0)
            return math.hypot(px - t * dx, py - t * dy)

        for kk in range(k, 0, -1):
            j = min(self.start + kk, m)
            dx, dy = r[j, 0] - x, r[j, 1] - y
            len2 = dx * dx + dy * dy
            if len2 < 1e-18 or all(off_chord(i, dx, dy, len2) <= tol for i in range(self.idx, j)):
                return kk
        return 0


def corridor_on_road(x0: float, y0: float, x1: float, y1: float, half_width: float, drivable) -> bool:
    """True when the straight corridor of half-width ``half_width`` from (x0, y0) to (x1, y1)
    lies on the paved road: ``drivable(x, y)`` holds at its centreline and both edges every
    ``CHORD_STEP`` metres, ends included."""
    dx, dy = x1 - x0, y1 - y0
    length = math.hypot(dx, dy)
    n = max(1, int(math.ceil(length / CHORD_STEP)))
    if length > 1e-9:
        nx, ny = -dy / length * half_width, dx / length * half_width
    else:
        nx = ny = 0.0
    for i in range(n + 1):
        t = i / n
        px, py = x0 + t * dx, y0 + t * dy
        if not (drivable(px, py) and drivable(px + nx, py + ny) and drivable(px - nx, py - ny)):
            return False
    return True


def lanes_across(lateral_point, x: float, y: float, psi: float) -> dict[int, tuple[float, float, float, float]]:
    """Every same-direction lane beside the point (x, y, psi) of a lane centre, found by walking
    ``lateral_point`` left and right: {n: (x, y, psi, offset)}, n lanes to the right (n < 0: to the
    left, 0: the point itself), offset the lane centre's signed distance from the point, left
    positive. Inside a junction ``lateral_point`` finds nothing, and only the point itself is there."""
    c, s = math.cos(psi), math.sin(psi)
    out = {0: (x, y, psi, 0.0)}
    for side in (-1, 1):
        px, py, ppsi, n = x, y, psi, 0
        while True:
            q = lateral_point(px, py, ppsi, side)
            if q is None:
                break
            n += side
            px, py, ppsi = float(q[0]), float(q[1]), float(q[2])
            if n in out:     # a map whose neighbour links loop: stop at the first repeat
                break
            out[n] = (px, py, ppsi, -(px - x) * s + (py - y) * c)
    return out


def decode_action(action, tracker: WaypointTracker, cfg: ActionConfig, lateral_point,
                  ego=None, drivable=None) -> tuple[np.ndarray, bool]:
    """MultiDiscrete action -> x_IMR = [x, y, v, psi] (eq. 31), and whether a lane change was taken.

    ``lateral_point(x, y, psi, side)`` gives the matching point on the adjacent lane or None;
    where there is no adjacent lane the waypoint stays (and it does not count as a lane change).
    A3 counts from the waypoint's own lane (``cfg.lane_change_from`` "route"); with "ev", from the
    lane beside the waypoint whose centre is nearest the EV's offset from its route
    (``lanes_across``): "keep" holds the lane the EV is in, and a change lasts until the EV is
    nearer the new lane's centre, after which "keep" holds that one; with "chosen", from the lane
    the episode's decisions have chosen so far, ``tracker.lane`` lanes beside the route (0 at the
    start, clamped to the lanes beside the waypoint, so inside a junction it returns to the
    route): "keep" holds that lane, a change moves it one lane further and is remembered, so one
    decision commits a whole lane change. With either, two changes reach the lane two over.
    With "chosen" and ``cfg.lane_change_commit`` set, A3 reads "keep" while the EV's offset from
    its route lies farther than that from the chosen lane's centre: a change is driven to its end
    before the next one counts, so decisions 0.3 s apart cannot weave the car between lanes; with
    ``cfg.lane_change_commit_holds`` "reversals" only a change back to the side the EV comes from
    is held, and a second change onwards, to the lane two over, counts at once.
    With ``cfg.zero_speed == "hold"`` a zero speed (A2 = 0 m/s) means "stop, facing along the
    route", whatever A1 and A3 say: x_IMR is at 0 m/s with the route's heading, at the EV's own
    position (``ego`` = [x, y, v, psi]; ``cfg.hold_decel`` None) or, with ``cfg.hold_decel`` set,
    where the EV comes to rest braking at that deceleration: v² / (2 hold_decel) further along the
    route, at the EV's offset from it (``WaypointTracker.ahead``). The route's heading, not the
    EV's own, because a stop ordered inside a turn brakes over a few metres: holding the current
    heading would straighten the wheel there and leave the lane. A moving EV passes its own
    position within a tick, after which that target lies behind it and the NMPC's position term
    turns the car towards it; the stop ahead is a point the EV reaches by braking alone. With ``cfg.chord_tol``
    set, A1 is limited to the farthest of WP0..WP_A1 that passes the chord limit:
    ``cfg.chord_rule`` "route", the waypoint's chord from the EV passes every route point before
    it within chord_tol (`WaypointTracker.chord_limited`), before any lane change is applied;
    "road", the reference the waypoint decodes to (its lane change applied) is reached from the
    EV along a straight corridor of half-width chord_tol on the paved road (``corridor_on_road``
    with ``drivable(x, y)``, the map's test); WP0 always passes. Where WP0 is
    (``cfg.min_lookahead``) is the tracker's, built by ``WaypointTracker.for_action(route, cfg)``.
    With ``cfg.reach_time`` set, A1 is also limited to the farthest of WP0..WP_A1 no farther
    ahead of the EV (``WaypointTracker.ahead_of``) than the distance A2's speed covers in that
    time, or than ``REACH_PER_LATERAL`` times the decoded waypoint's lateral offset from the EV,
    whichever is more: the NMPC weighs the reference's position against its speed, so a far
    waypoint pulls the EV well above the speed A2 asks for, and with the reach bounded A2 sets the
    speed; a lane change keeps room to be made in.
    """
    a1, a2, a3 = int(action[0]), int(action[1]), int(action[2])
    if not (0 <= a1 < cfg.n_waypoints and 0 <= a2 < len(cfg.speeds) and 0 <= a3 < len(cfg.lane_change)):
        raise ValueError(f"action {tuple(action)} outside MultiDiscrete({[cfg.n_waypoints, len(cfg.speeds), len(cfg.lane_change)]})")
    if cfg.zero_speed == "hold" and cfg.speeds[a2] == 0.0:
        if ego is None:
            raise ValueError("action.zero_speed 'hold' needs the EV pose (ego) to decode a stop")
        if cfg.hold_decel is None:
            return np.array([float(ego[0]), float(ego[1]), 0.0, tracker.heading_here()], dtype=np.float64), False
        v = max(float(ego[2]), 0.0)
        hx, hy, hpsi = tracker.ahead(float(ego[0]), float(ego[1]), v * v / (2.0 * cfg.hold_decel))
        return np.array([hx, hy, 0.0, hpsi], dtype=np.float64), False
    reach = None
    if cfg.reach_time is not None:
        if ego is None:
            raise ValueError("action.reach_time needs the EV pose (ego) to decode a waypoint")
        reach = float(cfg.speeds[a2]) * float(cfg.reach_time)
    side = cfg.lane_change[a3]
    chosen = cfg.lane_change_from == "chosen"
    from_ev = cfg.lane_change_from == "ev"
    commit = cfg.lane_change_commit if chosen else None
    if from_ev or commit is not None:
        if ego is None:
            what = "lane_change_from 'ev'" if from_ev else "lane_change_commit"
            raise ValueError(f"action.{what} needs the EV pose (ego) to decode a lane change")
        _, px, py = tracker.station(float(ego[0]), float(ego[1]))
        rpsi = tracker.heading_here()
        # the EV's signed offset from its route, left positive: the lane it is in is the one
        # whose centre lies at the nearest offset from the waypoint
        ev_off = -(float(ego[0]) - px) * math.sin(rpsi) + (float(ego[1]) - py) * math.cos(rpsi)
    road_rule = cfg.chord_tol is not None and cfg.chord_rule == "road"
    if cfg.chord_tol is not None:
        if ego is None:
            raise ValueError("action.chord_tol needs the EV pose (ego) to decode a waypoint")
        if road_rule and drivable is None:
            raise ValueError("action.chord_rule 'road' needs the map's drivable(x, y) to decode a waypoint")
        if not road_rule:
            a1 = tracker.chord_limited(a1, float(ego[0]), float(ego[1]), float(cfg.chord_tol))
    cands = tracker.candidates()
    for k in range(a1, -1, -1):
        wx, wy, wpsi = (float(c) for c in cands[k])
        changed = False
        if chosen or from_ev:
            lanes = lanes_across(lateral_point, wx, wy, wpsi)
            if chosen:
                here = min(max(tracker.lane, min(lanes)), max(lanes))
                if commit is not None and abs(ev_off - lanes[here][3]) > commit:
                    # the last change is still under way: it finishes first ("all"), or at least
                    # is not reversed ("reversals"; lanes to the right lie at lower offsets)
                    under_way = 1 if lanes[here][3] < ev_off else -1
                    if cfg.lane_change_commit_holds == "all" or side == -under_way:
                        side = 0
            else:
                here = min(lanes, key=lambda n: abs(lanes[n][3] - ev_off))
            there = here + int(side)
            if there != here and there in lanes:
                changed = True
            else:
                there = here
            wx, wy, wpsi = lanes[there][:3]
        elif side != 0:
            p = lateral_point(wx, wy, wpsi, int(side))
            if p is not None:
                wx, wy, wpsi = float(p[0]), float(p[1]), float(p[2])
                changed = True
        if k > 0 and reach is not None:
            rpsi = float(cands[k][2])
            lateral = abs(-(wx - ego[0]) * math.sin(rpsi) + (wy - ego[1]) * math.cos(rpsi))
            if tracker.ahead_of(k, float(ego[0]), float(ego[1])) > max(reach, REACH_PER_LATERAL * lateral):
                continue
        if not road_rule or k == 0 or corridor_on_road(float(ego[0]), float(ego[1]), wx, wy,
                                                       float(cfg.chord_tol), drivable):
            break
    if chosen:
        tracker.lane = there
    return np.array([wx, wy, float(cfg.speeds[a2]), wpsi], dtype=np.float64), changed


def idle_share(cfg: RewardConfig, v: float) -> float:
    """The share of ``idle_clear`` a tick at EV speed ``v`` pays while the junction is clear:
    with ``go_speed`` 0 (a stand test) 1 below ``idle_speed`` and 0 above; with ``go_speed`` > 0
    the speed's shortfall from it, 1 - v / go_speed (0 at or above), so that creeping pays part
    of the price and not only a stand."""
    if cfg.go_speed > 0.0:
        return max(0.0, 1.0 - float(v) / cfg.go_speed)
    return 1.0 if v < cfg.idle_speed else 0.0


def step_reward(cfg: RewardConfig, lane_change: bool, outcome: str | None = None, n_sv: int = 0,
                n_pcp: int = 0, ev_speed: float = 0.0, dist_to_goal: float = 0.0) -> float:
    """Eq. (26)-(28) for one decision: the per-step and lane-change terms, plus the terminal
    term when ``outcome`` is set. Shared by the environment and the ROS planner node, which
    reports episode returns to the curriculum. With ``timeout_mode: truncate`` a timeout adds
    nothing: the episode is cut, not failed (see env.yaml)."""
    r = cfg.step + (cfg.lane_change if lane_change else 0.0)
    if outcome is None or (outcome == "timeout" and not cfg.timeout_terminal):
        return r
    if outcome == "success":
        return r + cfg.success_base + cfg.alpha1 * n_sv + cfg.alpha2 * n_pcp
    if outcome not in ("collision", "timeout"):
        raise ValueError(f"unknown outcome {outcome!r}")
    r += min(cfg.r_f_max, cfg.alpha3 / max(float(dist_to_goal), 1e-3))
    if outcome == "collision":
        r += cfg.collision_base + cfg.alpha4 * n_sv * float(ev_speed)
    else:
        r += cfg.timeout
    return r
