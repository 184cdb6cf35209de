"""Scripted reference EV drivers: yardsticks for how hard the SVs make the world.

"go" follows the route at a fixed speed ignoring everyone (pure pursuit + P speed loop);
"yield" does the same but stops before the junction until no SV is within a safe time
gap of (or inside) the junction, then commits. Both use only what the EV may observe
(SV positions, speeds, headings), never SV goals or styles.
"""
from __future__ import annotations

import math

import numpy as np

from .config import DriverConfig

DRIVERS = ("go", "yield")


def junction_threatened(world, cfg: DriverConfig) -> bool:
    """The "yield" rule's threat test: an active SV within ``watch_distance`` of the junction
    centre that is inside the junction box or less than ``safe_time_gap`` from it at its own
    speed (``RoadMap.time_to_box``). False on a map without a junction. It reads the SVs' true
    states, so outside the scripted drivers it is privileged information (training rewards only,
    never the policy's observation)."""
    road = world.road
    if road.kind != "four_way":
        return False
    for st, active in zip(world.sv_states(), world.sv_active):
        if not active:
            continue
        x, y, v, psi = st
        if math.hypot(x, y) > cfg.watch_distance:
            continue
        if road.time_to_box(x, y, v, psi) < cfg.safe_time_gap:
            return True
    return False


def lead_vehicle(world) -> tuple[float, float] | None:
    """The SV ahead in the EV's lane: (bumper-to-bumper gap, its speed along the EV's heading,
    0 or more) of the nearest active SV ahead of the EV (in the EV's frame) within half a lane
    width of its heading line; None when there is none. It reads the SVs' true states (training
    rewards only, never the policy's observation)."""
    x, y, _, psi = world.ego_tuple()
    c, s = math.cos(psi), math.sin(psi)
    half = 0.5 * world.road.lane_width
    lead_dx, lead_v = math.inf, 0.0
    for st, active in zip(world.sv_states(), world.sv_active):
        if not active:
            continue
        dx = (st[0] - x) * c + (st[1] - y) * s
        dy = -(st[0] - x) * s + (st[1] - y) * c
        if 0.0 < dx < lead_dx and abs(dy) < half:
            lead_dx, lead_v = dx, max(st[2] * math.cos(st[3] - psi), 0.0)
    if not math.isfinite(lead_dx):
        return None
    return max(lead_dx - world.cfg.vehicle.length, 0.0), lead_v


def closing_on_lead(world, cfg: DriverConfig) -> bool:
    """Whether the EV closes on the SV ahead in its lane (``lead_vehicle``) too fast to stop
    behind it: its speed along the EV's heading is below the EV's by more than braking at
    ``stop_decel`` removes over the bumper-to-bumper gap less ``stop_margin``:
    v² − v_lead² > 2 b (gap − margin). The same kind of test as the yield rule's stop before the
    junction, applied to a lead vehicle. Privileged, like ``lead_vehicle``."""
    lead = lead_vehicle(world)
    v = world.ego_tuple()[2]
    if lead is None or v <= lead[1]:
        return False
    gap = max(lead[0] - cfg.stop_margin, 0.0)
    return v * v - lead[1] * lead[1] > 2.0 * cfg.stop_decel * gap


def queued_behind_lead(world, gap: float) -> bool:
    """Whether an SV ahead in the EV's lane (``lead_vehicle``) is within ``gap`` metres of the
    EV's front bumper: an EV slow there is queueing behind it, not idling on a clear road.
    Privileged, like ``lead_vehicle``."""
    lead = lead_vehicle(world)
    return lead is not None and lead[0] <= gap


def blocked_lanes(world, slow_speed: float, reach: float) -> set[int] | None:
    """The lanes (indices across the carriageway) of the EV's carriageway that a slow SV blocks:
    an active SV in the lane whose centre lies ahead of the EV's (along the EV's heading, at most
    ``reach`` metres) and whose speed is below ``slow_speed``. None where the EV is on no lane
    (inside a junction). It reads the SVs' true states and lanes (training rewards and
    yardsticks only, never the policy's observation)."""
    road = world.road
    x, y, _, psi = world.ego_tuple()
    here = road.lane_index(x, y)
    if here is None:
        return None

    def carriageway(lane_id):       # the lanes of one carriageway share kind and arm
        return road.lanes[lane_id].kind, road.lanes[lane_id].arm
    way = carriageway(here[0])
    c, s = math.cos(psi), math.sin(psi)
    blocked = set()
    for st, active in zip(world.sv_states(), world.sv_active):
        if not active or st[2] >= slow_speed:
            continue
        ahead = (st[0] - x) * c + (st[1] - y) * s
        lane = road.lane_index(float(st[0]), float(st[1]))
        if 0.0 < ahead <= reach and lane is not None and carriageway(lane[0]) == way:
            blocked.add(lane[1])
    return blocked


def lanes_to_free_lane(world, slow_speed: float, reach: float) -> int | None:
    """How many lanes lie between the EV's lane and the nearest lane of its carriageway that no
    slow SV blocks (``blocked_lanes``): 0 when its own lane is free. None where the EV is on no
    lane (inside a junction) or every lane is blocked: there is no lane to move towards."""
    blocked = blocked_lanes(world, slow_speed, reach)
    if blocked is None:
        return None
    x, y, _, _ = world.ego_tuple()
    here = world.road.lane_index(x, y)[1]
    free = [k for k in range(world.road.n_lanes) if k not in blocked]
    return min(abs(k - here) for k in free) if free else None


def junction_distance(world, y: float | None = None) -> float:
    """Distance from the EV's front bumper to the edge of the junction box (the EV approaches
    from the south); +inf on a map without a junction."""
    H = getattr(world.road, "H", None)
    if H is None:
        return math.inf
    if y is None:
        y = world.ego_tuple()[1]
    return -H - (y + 0.5 * world.cfg.vehicle.length)


def stop_line_distance(world, cfg: DriverConfig, y: float | None = None) -> float:
    """Distance from the EV's front bumper to its stop line, ``stop_margin`` before the junction
    box; +inf on a map without a junction."""
    return junction_distance(world, y) - cfg.stop_margin

class GoDriver:
    def __init__(self, world, config: DriverConfig | None = None):
        self.world = world
        self.cfg = config or DriverConfig.load()
        self._i = 0
        self._route = world.route

    def reset(self):
        self._i = 0
        self._route = self.world.route

    def _steer(self, x, y, v, psi):
        r = self._route
        n = len(r)
        i = self._i
        # monotone nearest-waypoint search (the EV never drives backwards along the route)
        best = (r[i, 0] - x) ** 2 + (r[i, 1] - y) ** 2
        while i + 1 < n:
            d = (r[i + 1, 0] - x) ** 2 + (r[i + 1, 1] - y) ** 2
            if d > best:
                break
            best, i = d, i + 1
        self._i = i
        ld = max(self.cfg.lookahead_min, v * self.cfg.lookahead_time)
        j = i
        while j + 1 < n and math.hypot(r[j, 0] - x, r[j, 1] - y) < ld:
            j += 1
        tx, ty = r[j, 0], r[j, 1]
        alpha = math.atan2(ty - y, tx - x) - psi
        dist = max(math.hypot(tx - x, ty - y), 1e-3)
        L = self.world.cfg.vehicle.wheelbase
        return math.asin(max(-1.0, min(1.0, L * math.sin(alpha) / dist)))

    def target_speed(self, x, y, v, psi):
        return self.cfg.target_speed

    def act(self) -> np.ndarray:
        x, y, v, psi = self.world.ego_tuple()
        delta = self._steer(x, y, v, psi)
        a = self.cfg.speed_gain * (self.target_speed(x, y, v, psi) - v)
        return np.array([a, delta])


class YieldDriver(GoDriver):
    def reset(self):
        super().reset()
        self._committed = False

    def __init__(self, world, config=None):
        super().__init__(world, config)
        self._committed = False

    def _threat(self) -> bool:
        return junction_threatened(self.world, self.cfg)

    def _stop_distance(self, y):
        return stop_line_distance(self.world, self.cfg, y)

    def act(self) -> np.ndarray:
        x, y, v, psi = self.world.ego_tuple()
        delta = self._steer(x, y, v, psi)
        a = self.cfg.speed_gain * (self.cfg.target_speed - v)
        if getattr(self.world.road, "H", None) is not None and not self._committed:
            d = self._stop_distance(y)
            if not self._threat():
                if d <= self.cfg.stop_margin:      # at the line with a clear junction: go
                    self._committed = True
            elif d > 0.0:
                if v * v >= 2.0 * self.cfg.stop_decel * d * 0.8:   # follow the stopping profile
                    a = -v * v / (2.0 * max(d, 0.05))
                else:
                    a = min(a, self.cfg.speed_gain * (math.sqrt(2.0 * self.cfg.stop_decel * d) - v))
            else:                                   # over the line while threatened: stand still
                a = -v / self.world.dt
        return np.array([a, delta])


def make_driver(name: str, world, config: DriverConfig | None = None):
    if name == "go":
        return GoDriver(world, config)
    if name == "yield":
        return YieldDriver(world, config)
    raise ValueError(f"unknown driver {name!r}; expected one of {DRIVERS}")


def run_episode(world, scenario, driver: str = "go", frames=None, config=None):
    """Reset ``world`` to ``scenario`` and drive it to the end; returns the last StepResult.
    ``frames`` (a callable) is called after reset and after every step (for GIFs)."""
    world.reset(scenario)
    drv = make_driver(driver, world, config)
    if frames:
        frames(world)
    while True:
        res = world.step(drv.act())
        if frames:
            frames(world)
        if res.done:
            return res
