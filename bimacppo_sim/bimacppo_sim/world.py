"""The world: EV on the kinematic bicycle model (paper eq. (1)-(2)) among interactive SVs.

SVs follow precomputed arc-length paths with IDM; conflicts among SVs are resolved by a
first-come-first-served reservation of conflict zones (an SV commits to all its zones at
once, only when none is held and no earlier-ticketed SV would arrive within its style's
gap), so SVs never stop inside the junction for each other. Towards the EV (whose route
they do not know) they use a constant-turn-rate prediction and a style-dependent gap
acceptance: aggressive ones never yield at conflict points, conservative ones with a
wide margin. Every random draw happens in reset() from numpy's Generator(seed), in a
fixed order, so a scenario gives bit-identical trajectories.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import STYLES, WorldConfig
from bimacppo_common.conventions import TASKS, wrap_angle

from .geometry import box_corners, boxes_overlap
from .road import RoadMap, load_map


@dataclass(frozen=True)
class Scenario:
    """Omega_ij = (n_sv = i, task = TASKS[j]) plus a seed; options for tests/fine-tuning:
    ev_present=False runs SVs alone; ev_lane fixes the EV's start lane; n_slow sets how
    many SVs drive slowly (None: random, used on the overtaking map)."""
    n_sv: int
    task: str
    seed: int
    ev_present: bool = True
    ev_lane: int | None = None
    n_slow: int | None = 0

    def __post_init__(self):
        for name in ("n_sv", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise ValueError(f"Scenario.{name} must be an integer, got {v!r}")
            if v < 0:
                raise ValueError(f"Scenario.{name} must be >= 0, got {v}")
        if self.task not in TASKS:
            raise ValueError(f"unknown task {self.task!r}; expected one of {TASKS}")
        if not isinstance(self.ev_present, bool):
            raise ValueError("Scenario.ev_present must be a bool")
        for name in ("ev_lane", "n_slow"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0):
                raise ValueError(f"Scenario.{name} must be None or an integer >= 0, got {v!r}")
        if self.n_slow is not None and self.n_slow > self.n_sv:
            raise ValueError(f"Scenario.n_slow = {self.n_slow} exceeds n_sv = {self.n_sv}")


def draw_n_slow(seed: int, n_sv: int, n_slow_max: int) -> int:
    """How many SVs drive slowly in the scenario of ``seed`` with at most ``n_slow_max`` slow
    (the overtaking protocol, paper §IV-C): uniform in 0..min(n_sv, n_slow_max), a function of
    the seed alone (drawn from a SeedSequence child of it, a stream independent of the world's),
    so training, evaluation and the world node meet the same scenario for a seed."""
    rng = np.random.default_rng(np.random.SeedSequence(int(seed)).spawn(1)[0])
    return int(rng.integers(0, min(int(n_sv), int(n_slow_max)) + 1))


@dataclass
class StepResult:
    done: bool
    outcome: str | None          # None while running, else one of OUTCOMES
    collided_with: str | None    # SV id, "offroad", or None
    time: float
    steps: int
    sv_collisions: int           # distinct SV-SV pairs that overlapped so far (diagnostic)


class _SV:
    __slots__ = ("id", "route", "path", "style", "maneuver", "s", "v", "x", "y", "psi", "acc", "active",
                 "v_des", "a_max", "b", "b_max", "T", "s0", "gap", "yield_ev", "ev_gap", "sqrt_ab",
                 "ticket", "committed", "conf", "gate", "slow", "brake_crossing", "fcfs")


class World:
    """See module docstring and docs/world.md."""

    def __init__(self, road: RoadMap | str, config: WorldConfig | None = None):
        self.road = road if isinstance(road, RoadMap) else load_map(road)
        self.cfg = config or WorldConfig.load()
        veh = self.cfg.vehicle
        self.dt = self.cfg.dt
        self._hl, self._hw = 0.5 * veh.length, 0.5 * veh.width
        self._r2 = (2.0 * math.hypot(self._hl, self._hw)) ** 2
        self._L = veh.wheelbase
        self.max_sv = self.road.max_sv
        sc = self.cfg.sv
        self._probs = np.array([sc.styles[s].probability for s in STYLES])
        self._probs = self._probs / self._probs.sum()
        self._reach = self._hl + self._hw + sc.conflict_margin
        self._preds = []
        self.scenario = None

    # ------------------------------------------------------------------ reset
    def reset(self, scenario: Scenario):
        if not isinstance(scenario, Scenario):
            raise ValueError(f"reset() needs a Scenario, got {type(scenario).__name__}")
        road, cfg = self.road, self.cfg
        if scenario.n_sv > road.max_sv:
            raise ValueError(f"n_sv = {scenario.n_sv} exceeds map {road.id!r} limit max_sv = {road.max_sv}")
        if scenario.task not in road.turns:
            raise ValueError(f"task {scenario.task!r} not available on map {road.id!r} "
                             f"(tasks: {sorted(road.turns)})")
        if scenario.ev_lane is not None and scenario.ev_lane >= road.n_lanes:
            raise ValueError(f"ev_lane = {scenario.ev_lane} but map {road.id!r} has {road.n_lanes} lanes")
        self.scenario = scenario
        rng = np.random.default_rng(scenario.seed)
        n = road.n_lanes
        # --- EV start, goal, route
        k = int(rng.integers(n)) if scenario.ev_lane is None else scenario.ev_lane
        d0 = float(rng.uniform(cfg.ev_start_distance_min, cfg.ev_start_distance_max))
        v0 = float(rng.uniform(cfg.ev_speed_min, cfg.ev_speed_max))
        if road.kind == "four_way":
            start_lane = f"{road.ev_arm}_in_{k}"
            s_start = road.arm_length - d0
            self.target_arm = road.exit_arm(road.ev_arm, scenario.task)
            pairs = road.turns[scenario.task]
            pair = next((p for p in pairs if p[0] == k), pairs[0])
            goal_lane = f"{self.target_arm}_out_{pair[1]}"
            s_goal = cfg.success_distance
        else:
            start_lane = f"road_{k}"
            s_start = d0
            self.target_arm = None
            goal_lane = start_lane
            s_goal = s_start + road.goal_ahead
        self.start_lane, self.goal_lane, self._s_goal = start_lane, goal_lane, s_goal
        x, y, psi = road.lane_point(start_lane, s_start)
        self.goal = np.array(road.lane_point(goal_lane, s_goal))
        # the same call the planner makes on its own map copy from the start and goal poses
        self.route, pts, conns = reference_route(road, (x, y), self.goal, cfg, with_polyline=True)
        self._route_poly = pts
        self.ev_connector = conns[0] if conns else None
        self._ev = [x, y, v0, psi]
        self._ev_present = scenario.ev_present
        self._ev_yaw_rate = 0.0
        self._ev_lane = start_lane
        self.ev_lane_change_count = 0
        # EV's nominal arrival profile (for SV spawn timing)
        route_cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
        # --- SVs
        self.svs = []
        sc = cfg.sv
        if road.kind == "four_way":
            arms = [road.sv_arms[i] for i in rng.permutation(len(road.sv_arms))[:scenario.n_sv]]
        else:
            arms = [int(i) for i in rng.permutation(n)[:scenario.n_sv]]
        n_slow = int(rng.integers(scenario.n_sv + 1)) if scenario.n_slow is None else scenario.n_slow
        for idx, arm in enumerate(arms):
            sv = _SV()
            sv.id = f"sv{idx}"
            sv.style = STYLES[int(rng.choice(len(STYLES), p=self._probs))]
            st = sc.styles[sv.style]
            if road.kind == "four_way":
                sv.maneuver = TASKS[int(rng.integers(3))]
                lp = road.turns[sv.maneuver]
                i_in, i_out = lp[int(rng.integers(len(lp)))]
                sv.route = road.sv_routes[(arm, sv.maneuver, i_in, i_out)]
            else:
                sv.maneuver = "straight"
                sv.route = road.sv_routes[("road", "straight", arm, arm)]
            sv.path = sv.route.path
            factor = float(rng.uniform(sc.spawn_speed_factor_min, sc.spawn_speed_factor_max))
            jitter = float(rng.uniform(-sc.spawn_time_jitter, sc.spawn_time_jitter))
            slow_f = float(rng.uniform(sc.slow_speed_factor_min, sc.slow_speed_factor_max))
            sv.slow = idx < n_slow
            sv.v_des = st.v_desired * (slow_f if sv.slow else 1.0)
            sv.a_max, sv.b, sv.b_max = st.a_max, st.b_comfortable, st.b_max
            sv.T, sv.s0, sv.gap = st.time_headway, st.min_gap, st.sv_gap
            sv.yield_ev, sv.ev_gap = st.yield_to_ev, st.ev_gap
            sv.brake_crossing = st.brake_for_crossing_ev
            sv.fcfs = st.respects_fcfs
            sv.sqrt_ab = 2.0 * math.sqrt(sv.a_max * sv.b)
            sv.v = sv.v_des * factor
            if road.kind == "four_way":
                sv.s = self._spawn_s(sv, pts, route_cum, v0, jitter)
            else:
                sv.s = s_start + float(rng.uniform(road.sv_ahead_min, road.sv_ahead_max))
            sv.x, sv.y, sv.psi = sv.path.pose(sv.s)
            sv.acc = 0.0
            sv.active = True
            sv.ticket = None
            sv.committed = False
            self.svs.append(sv)
        # --- pairwise conflict zones for this episode
        for i, a in enumerate(self.svs):
            a.conf = []
            for j, b in enumerate(self.svs):
                if i == j:
                    continue
                za = a.route.conflicts.get(b.route.key)
                zb = b.route.conflicts.get(a.route.key)
                if za is not None and zb is not None:
                    a.conf.append((b, za[0], za[1], zb[0], zb[1]))
            # waiting SVs hold at the junction entry (never mid-junction, where they would
            # block the EV's lanes), or before their first conflict if that comes earlier
            a.gate = (min(min(c[1] for c in a.conf), a.route.s_entry) - sc.stop_margin) if a.conf else math.inf
        self._tickets = 0
        self.sv_ids = [s.id for s in self.svs]
        self.sv_styles = [s.style for s in self.svs]
        self.sv_maneuvers = [s.maneuver for s in self.svs]
        self.n_pcp = 0
        if road.kind == "four_way" and self.ev_connector:
            self.n_pcp = sum(road.connector_conflicts(self.ev_connector, s.route.connector) for s in self.svs)
        self.time = 0.0
        self.steps = 0
        self.done = False
        self.outcome = None
        self._sv_pairs = set()
        return self

    def _spawn_s(self, sv, route_pts, route_cum, v0, jitter):
        """Place the SV so that it reaches its first conflict with the EV's route (or the
        junction) about when the EV would at its nominal speed, +- jitter: interaction."""
        cfg, path, r = self.cfg, sv.path, sv.route
        s_sv, s_ev = r.s_entry, None
        for p, c in zip(route_pts, route_cum):
            hit = path.lookup(float(p[0]), float(p[1]))
            if hit is not None and hit >= r.s_entry - self._reach:
                s_sv, s_ev = hit, c
                break
        if s_ev is None:          # no shared point: time the SV to the EV's junction entry
            inside = np.nonzero(np.maximum(np.abs(route_pts[:, 0]), np.abs(route_pts[:, 1]))
                                <= self.road.H + 1e-6)[0]
            s_ev = float(route_cum[inside[0]]) if len(inside) else float(route_cum[-1])
        a = cfg.vehicle.a_max
        vn = cfg.ev_nominal_speed
        d_acc = max(0.0, (vn * vn - v0 * v0) / (2 * a))
        t_ev = (s_ev / vn + (vn - v0) ** 2 / (2 * a * vn)) if s_ev > d_acc else \
            (-v0 + math.sqrt(v0 * v0 + 2 * a * s_ev)) / a
        t_target = t_ev + jitter
        s_max = max(0.0, r.s_entry - self._reach - cfg.sv.min_spawn_distance)
        s = min(s_sv, path.length)
        t = 0.0
        while s > 0.0 and t < t_target:
            i = min(int(s * path.inv_ds), path.n - 1)
            t += path.ds / max(min(sv.v, path.vcap[i]), cfg.sv.min_speed_for_eta)
            s -= path.ds
        return min(max(s, 0.0), s_max)

    # ------------------------------------------------------------------ step
    def step(self, action=None) -> StepResult:
        if self.scenario is None:
            raise RuntimeError("call reset(Scenario(...)) before step()")
        if self.done:
            raise RuntimeError("episode is over (done); call reset()")
        dt = self.dt
        ev = self._ev
        if self._ev_present:
            if action is None:
                raise ValueError("step() needs an action [a, delta] when the EV is present")
            try:
                a, delta = float(action[0]), float(action[1])
            except (TypeError, IndexError, ValueError):
                raise ValueError(f"action must be a sequence [a, delta], got {action!r}") from None
            if not (math.isfinite(a) and math.isfinite(delta)):
                raise ValueError(f"non-finite EV input a={a}, delta={delta}")
        if self.svs:
            self._update_svs()
        if self._ev_present:
            veh = self.cfg.vehicle
            a = min(max(a, veh.a_min), veh.a_max)
            delta = min(max(delta, -veh.delta_max), veh.delta_max)
            x, y, v, psi = ev
            h = psi + delta
            # eq. (1)-(2): explicit Euler from x_k; speed kept within physical bounds
            ev[0] = x + v * math.cos(h) * dt
            ev[1] = y + v * math.sin(h) * dt
            yaw = 2.0 * v / self._L * math.sin(delta)
            ev[3] = wrap_angle(psi + yaw * dt)
            ev[2] = min(max(v + a * dt, veh.v_min), veh.v_max)
            self._ev_yaw_rate = yaw
        self.time = round(self.time + dt, 9)
        self.steps += 1
        return self._check()

    def _check(self) -> StepResult:
        hl, hw, r2 = self._hl, self._hw, self._r2
        svs = self.svs
        for i in range(len(svs)):
            a = svs[i]
            if not a.active:
                continue
            for j in range(i + 1, len(svs)):
                b = svs[j]
                if b.active and boxes_overlap(a.x, a.y, a.psi, b.x, b.y, b.psi, hl, hw, r2):
                    self._sv_pairs.add((i, j))
        outcome, hit = None, None
        if self._ev_present:
            x, y, v, psi = self._ev
            for sv in svs:
                if sv.active and boxes_overlap(x, y, psi, sv.x, sv.y, sv.psi, hl, hw, r2):
                    outcome, hit = "collision", sv.id
                    break
            if outcome is None and self._offroad():
                outcome, hit = "collision", "offroad"
            lane = self.road.locate(x, y)
            if lane is not None:
                lid = lane[0]
                if lid != self._ev_lane and self._ev_lane is not None:
                    l_old = self.road.lanes[self._ev_lane]
                    if l_old.left == lid or l_old.right == lid:
                        self.ev_lane_change_count += 1
                self._ev_lane = lid
                if outcome is None and self._at_goal(lid, lane[1]):
                    outcome = "success"
        elif not any(s.active for s in svs):
            outcome = "success"
        if outcome is None and self.time >= self.cfg.time_limit - 1e-9:
            outcome = "timeout"
        if outcome is not None:
            self.done, self.outcome = True, outcome
        return StepResult(self.done, outcome, hit, self.time, self.steps, len(self._sv_pairs))

    def _at_goal(self, lid, s):
        if self.road.kind == "straight":
            return s >= self._s_goal
        if self.cfg.goal_any_lane:
            return lid.startswith(f"{self.target_arm}_out_") and s >= self.cfg.success_distance
        return lid == self.goal_lane and s >= self.cfg.success_distance

    def _offroad(self) -> bool:
        mode = self.cfg.offroad_check
        if mode == "off":
            return False
        x, y, _, psi = self._ev
        if mode == "centre":
            return not self.road.drivable(x, y)
        veh = self.cfg.vehicle
        return any(not self.road.drivable(px, py) for px, py in box_corners(x, y, psi, veh.length, veh.width))

    # ------------------------------------------------------------------ SV model
    def _update_svs(self):
        sc = self.cfg.sv
        dt, L = self.dt, 2.0 * self._hl
        vmin = sc.min_speed_for_eta
        ev_on = self._ev_present
        ex, ey, ev_v, epsi = self._ev
        reach = self._reach
        # constant-turn-rate prediction of the EV, shared by all SVs
        preds = self._preds
        preds.clear()
        if ev_on:
            px, py, ph, t = ex, ey, epsi, 0.0
            step = sc.ev_prediction_step
            while t <= sc.ev_prediction_horizon + 1e-9:
                preds.append((t, px, py, ph))
                px += ev_v * math.cos(ph) * step
                py += ev_v * math.sin(ph) * step
                ph += self._ev_yaw_rate * step
                t += step
        # FCFS tickets: drawn in order of arrival at request_distance before the gate
        newly = [s for s in self.svs if s.active and s.ticket is None and s.gate - s.s <= sc.request_distance]
        for s in sorted(newly, key=lambda q: ((q.gate - q.s) / max(q.v, vmin), q.id)):
            self._tickets += 1
            s.ticket = self._tickets
        order = sorted((s for s in self.svs if s.active),
                       key=lambda q: (q.ticket if q.ticket is not None else 1 << 30, q.id))
        delta = sc.idm_delta
        for sv in order:
            path = sv.path
            s, v = sv.s, sv.v
            i = int(s * path.inv_ds)
            if i >= path.n:
                i = path.n - 1
            v0 = sv.v_des if sv.v_des < path.vcap[i] else path.vcap[i]
            # leader: nearest vehicle whose centre lies on my path ahead
            gap, vl = math.inf, 0.0
            for o in self.svs:
                if o is sv or not o.active:
                    continue
                so = path.lookup(o.x, o.y)
                if so is not None and s < so < s + sc.lookahead:
                    g = so - s - L
                    if g < gap:
                        j = int(so * path.inv_ds)
                        vl = o.v * math.cos(o.psi - path.psis[j if j < path.n else path.n - 1])
                        gap = g
            ev_aligned = False
            if ev_on:
                so = path.lookup(ex, ey)
                if so is not None:
                    j = int(so * path.inv_ds)
                    c = math.cos(epsi - path.psis[j if j < path.n else path.n - 1])
                    ev_aligned = c > 0.7
                    if s < so < s + sc.lookahead and so - s - L < gap and (ev_aligned or sv.brake_crossing):
                        gap, vl = so - s - L, ev_v * c
            if vl < 0.0:
                vl = 0.0
            stop = math.inf
            # reservation among SVs
            if not sv.committed and sv.conf:
                granted = True
                for (o, a_i, b_i, a_j, b_j) in sv.conf:
                    if not o.active or o.s >= b_j or s >= b_i:
                        continue
                    if o.committed:
                        granted = False
                        break
                    if sv.fcfs and o.ticket is not None and (sv.ticket is None or o.ticket < sv.ticket):
                        t_o = _eta(a_j - o.s, o.v, o.a_max)
                        t_exit = _eta(b_i - s, v, sv.a_max)
                        if t_o < t_exit + sv.gap:
                            granted = False
                            break
                if not granted:
                    stop = sv.gate
                elif sv.gate - s <= v * v / (2.0 * sv.b) + sc.commit_margin:
                    sv.committed = True
            # gap acceptance towards the EV
            if ev_on and sv.yield_ev and not ev_aligned:
                for (t, px, py, ph) in preds:
                    sc_ = path.lookup(px, py)
                    if sc_ is None:
                        continue
                    if sc_ > s:
                        d_in = sc_ - reach - s
                        if d_in > 0.0:
                            vv = v if v > vmin else vmin
                            w = reach / (ev_v if ev_v > vmin else vmin)
                            t_in, t_out = d_in / vv, (sc_ + reach - s) / vv
                            if t_in < t + w + sv.ev_gap and t_out > t - w - sv.ev_gap:
                                line = sc_ - reach - sc.stop_margin
                                if v * v <= 2.0 * sv.b_max * (line - s):
                                    stop = min(stop, line)            # can stop before the zone
                                elif v < sc.creep_speed:
                                    stop = min(stop, s + 0.5 * v * v / sv.b_max)   # hold here
                    break
            # IDM with the leader and the virtual stop line (a standing obstacle)
            acc = 1.0 - (v / v0) ** delta if v0 > 0.0 else -1.0
            acc *= sv.a_max
            if gap < math.inf:
                ss = sv.s0 + v * sv.T + v * (v - vl) / sv.sqrt_ab
                g = gap if gap > 0.1 else 0.1
                acc -= sv.a_max * (ss / g) ** 2 if ss > 0.0 else 0.0
            if stop < math.inf:
                ss = sv.s0 + v * sv.T + v * v / sv.sqrt_ab
                g = stop - s + sv.s0
                g = g if g > 0.1 else 0.1
                acc2 = sv.a_max * (1.0 - (v / v0) ** delta if v0 > 0 else -1.0) - sv.a_max * (ss / g) ** 2
                if acc2 < acc:
                    acc = acc2
            if acc < -sv.b_max:
                acc = -sv.b_max
            sv.acc = acc
        for sv in self.svs:
            if not sv.active:
                continue
            v, acc = sv.v, sv.acc
            nv = v + acc * dt
            if nv < 0.0:
                ds = -0.5 * v * v / acc if acc < 0.0 else 0.0
                nv = 0.0
            else:
                ds = v * dt + 0.5 * acc * dt * dt
            sv.v = nv
            sv.s += ds
            if sv.s >= sv.path.length:
                sv.s = sv.path.length
                sv.active = False
            sv.x, sv.y, sv.psi = sv.path.pose(sv.s)

    # ------------------------------------------------------------------ accessors
    @property
    def ego(self) -> np.ndarray:
        return np.array(self._ev)

    def ego_tuple(self):
        """(x, y, v, psi) as floats: allocation-free access for hot loops."""
        return tuple(self._ev)

    def sv_states(self) -> np.ndarray:
        return np.array([[s.x, s.y, s.v, s.psi] for s in self.svs], dtype=float).reshape(len(self.svs), 4)

    @property
    def sv_active(self):
        return [s.active for s in self.svs]

    @property
    def ev_lane(self):
        """Id of the straight lane the EV was last seen on (its lane during the junction)."""
        return self._ev_lane

    def dist_to_goal(self) -> float:
        """Euclidean distance from the EV centre to the goal point."""
        return math.hypot(self._ev[0] - self.goal[0], self._ev[1] - self.goal[1])


def _eta(d, v, a):
    """Time to cover d from speed v at constant acceleration a (optimistic arrival)."""
    if d <= 0.0:
        return 0.0
    return (-v + math.sqrt(v * v + 2.0 * a * d)) / a


def reference_route(road: RoadMap, start_xy, goal_xy, config: WorldConfig | None = None,
                    with_polyline: bool = False):
    """The EV's A* reference waypoint set (M, 3) [x, y, psi] from a start position to a goal
    position, both on straight lanes: the world computes it at reset and the planner
    recomputes it from /ego/odom and /goal_pose, so both must go through this one function.
    The route runs ``route_tail`` m past the goal so that A1 still has waypoints ahead there.
    A start or goal off the straight lanes, or a start that cannot reach the goal, is a
    ValueError; a planner that first sees an episode late has its own fallbacks
    (``bimacppo_planner.agent.route_for``)."""
    cfg = config or WorldConfig.load()
    start = road.locate(float(start_xy[0]), float(start_xy[1]))
    goal = road.locate(float(goal_xy[0]), float(goal_xy[1]))
    if start is None or goal is None:
        which = "start" if start is None else "goal"
        raise ValueError(f"route {which} ({float((start_xy if start is None else goal_xy)[0]):.2f}, "
                         f"{float((start_xy if start is None else goal_xy)[1]):.2f}) is not on a straight lane "
                         f"of map {road.id!r}")
    pts, conns, _ = road.plan_route(start[0], start[1], goal[0], route_end(road, goal, cfg))
    route = resample_route(pts, cfg.waypoint_spacing)
    return (route, pts, conns) if with_polyline else route


def route_end(road: RoadMap, goal, cfg: WorldConfig) -> float:
    """Station on the goal's lane (``goal`` = road.locate of the goal) where a route ends:
    ``route_tail`` past the goal, at most the lane's end."""
    return min(goal[1] + cfg.route_tail, road.lanes[goal[0]].length)


def resample_route(pts, spacing):
    """Waypoints every ``spacing`` m along the polyline, as (M, 3) [x, y, psi]."""
    pts = np.asarray(pts, float)
    seg = np.hypot(*np.diff(pts, axis=0).T)
    keep = np.concatenate([[True], seg > 1e-9])
    pts = pts[keep]
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    s = np.arange(0.0, cum[-1] + 1e-9, spacing)
    x = np.interp(s, cum, pts[:, 0])
    y = np.interp(s, cum, pts[:, 1])
    # heading of the polyline at each station (segment containing it)
    j = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(pts) - 2)
    d = pts[j + 1] - pts[j]
    psi = np.arctan2(d[:, 1], d[:, 0])
    return np.column_stack([x, y, psi])
