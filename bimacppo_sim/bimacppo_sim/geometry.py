"""Scalar-fast geometry: arc-length paths, oriented-box overlap (SAT), polyline crossings.

Per-step code runs on Python floats with ``math`` (numpy's per-call overhead dominates
on 2-4 element arrays); numpy is used only for one-off precomputation at map load.
"""
from __future__ import annotations

import math

import numpy as np

from bimacppo_common.conventions import wrap_angle

BEZIER_CIRCLE_K = 4.0 / 3.0 * math.tan(math.pi / 8.0)  # cubic Bezier ~ quarter circle


def bezier_connector(p0, h0, p1, h1, step=0.25):
    """Cubic Bezier from pose (p0, h0) to (p1, h1); for a symmetric 90-degree turn it
    matches a circular arc to 0.03 %, for a straight crossing it is the segment."""
    p0 = np.asarray(p0, float)
    p1 = np.asarray(p1, float)
    t0 = np.array([math.cos(h0), math.sin(h0)])
    t1 = np.array([math.cos(h1), math.sin(h1)])
    cross = t0[0] * t1[1] - t0[1] * t1[0]
    if abs(cross) < 1e-9:                          # parallel: straight line (or S-curve)
        d = np.linalg.norm(p1 - p0) / 3.0
        c0, c1 = p0 + d * t0, p1 - d * t1
    else:                                          # tangent lines meet at the corner point
        w = p1 - p0
        lam = (w[0] * t1[1] - w[1] * t1[0]) / cross
        mu = (w[0] * t0[1] - w[1] * t0[0]) / cross
        # corner = p0 + lam*t0 = p1 + mu*t1 (mu < 0: the corner lies behind p1)
        c0 = p0 + BEZIER_CIRCLE_K * lam * t0
        c1 = p1 + BEZIER_CIRCLE_K * mu * t1
    chord = np.linalg.norm(p1 - p0)
    n = max(8, int(math.ceil(1.6 * chord / step)))
    t = np.linspace(0.0, 1.0, n)[:, None]
    pts = ((1 - t) ** 3) * p0 + 3 * ((1 - t) ** 2) * t * c0 + 3 * (1 - t) * t ** 2 * c1 + t ** 3 * p1
    return pts


def polyline_length(pts) -> float:
    pts = np.asarray(pts, float)
    return float(np.sum(np.hypot(*np.diff(pts, axis=0).T)))


class Path:
    """A polyline resampled at a uniform arc-length step: pose(s) is O(1), no bisection."""

    __slots__ = ("xs", "ys", "psis", "kappa", "ds", "inv_ds", "n", "length", "grid", "grid_cell",
                 "vcap", "_seg_psi")

    def __init__(self, points, ds: float):
        pts = np.asarray(points, float)
        keep = np.concatenate([[True], np.hypot(*np.diff(pts, axis=0).T) > 1e-9])
        pts = pts[keep]
        if len(pts) < 2:
            raise ValueError("a path needs at least two distinct points")
        cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
        length = float(cum[-1])
        n = max(2, int(round(length / ds)) + 1)
        s = np.linspace(0.0, length, n)
        xs = np.interp(s, cum, pts[:, 0])
        ys = np.interp(s, cum, pts[:, 1])
        seg = np.arctan2(np.diff(ys), np.diff(xs))
        psi = np.concatenate([seg, seg[-1:]])
        self.length = length
        self.n = n
        self.ds = length / (n - 1)
        self.inv_ds = 1.0 / self.ds
        self.xs, self.ys, self.psis = xs.tolist(), ys.tolist(), psi.tolist()
        self._seg_psi = psi
        # curvature over a ~2 m window: resampling a sampled curve makes vertex spikes
        w = max(1, int(round(1.0 / self.ds)))
        un = np.unwrap(psi)
        lo = np.clip(np.arange(n) - w, 0, n - 1)
        hi = np.clip(np.arange(n) + w, 0, n - 1)
        self.kappa = (un[hi] - un[lo]) / np.maximum((hi - lo) * self.ds, 1e-9)
        self.grid = None
        self.grid_cell = None
        self.vcap = None

    def pose(self, s: float):
        """(x, y, psi) at arc length s (clamped to the path)."""
        f = s * self.inv_ds
        i = int(f)
        if i >= self.n - 1:
            i = self.n - 1
            return self.xs[i], self.ys[i], self.psis[i]
        if f <= 0.0:
            return self.xs[0], self.ys[0], self.psis[0]
        t = f - i
        xs, ys = self.xs, self.ys
        return xs[i] + t * (xs[i + 1] - xs[i]), ys[i] + t * (ys[i + 1] - ys[i]), self.psis[i]

    def points(self) -> np.ndarray:
        return np.column_stack([self.xs, self.ys])

    def build_speed_cap(self, a_lat: float):
        """Curve speed limit sqrt(a_lat/|kappa|), made reachable by braking at a_lat
        (backward pass), so IDM's desired speed anticipates every bend."""
        k = np.abs(self.kappa)
        vc = np.sqrt(a_lat / np.maximum(k, 1e-6))
        for i in range(self.n - 2, -1, -1):
            vc[i] = min(vc[i], math.sqrt(vc[i + 1] ** 2 + 2.0 * a_lat * self.ds))
        self.vcap = vc.tolist()

    def build_grid(self, cell: float, radius: float):
        """Point -> nearest arc length lookup for points within ``radius`` of the path:
        one dict access per query instead of a projection onto the polyline."""
        pts = self.points()
        lo = np.floor((pts.min(axis=0) - radius) / cell).astype(int)
        hi = np.floor((pts.max(axis=0) + radius) / cell).astype(int)
        # The cells searched: those within w cells of a path point's cell, which holds every
        # cell whose centre lies within radius of the path (not the whole bounding box, most of
        # which is far from a curved path); in the bounding box's row-major order.
        w = int(math.ceil(radius / cell)) + 1
        shape = hi - lo + 1
        ip = np.floor(pts / cell).astype(int) - lo
        near = np.zeros((int(shape[0]), int(shape[1])), dtype=bool)
        for dx in range(-w, w + 1):
            for dy in range(-w, w + 1):
                near[np.clip(ip[:, 0] + dx, 0, shape[0] - 1), np.clip(ip[:, 1] + dy, 0, shape[1] - 1)] = True
        cand = np.argwhere(near)
        keys_x = cand[:, 0] + lo[0]
        keys_y = cand[:, 1] + lo[1]
        centres = np.column_stack([(keys_x + 0.5) * cell, (keys_y + 0.5) * cell])
        best_d = np.full(len(centres), np.inf)
        best_s = np.zeros(len(centres))
        for start in range(0, len(pts), 256):
            chunk = pts[start:start + 256]
            d = np.hypot(centres[:, None, 0] - chunk[None, :, 0], centres[:, None, 1] - chunk[None, :, 1])
            j = np.argmin(d, axis=1)
            dj = d[np.arange(len(centres)), j]
            better = dj < best_d
            best_d[better] = dj[better]
            best_s[better] = (start + j[better]) * self.ds
        sel = best_d <= radius
        self.grid = {grid_key(int(a), int(b)): float(s)
                     for a, b, s in zip(keys_x[sel], keys_y[sel], best_s[sel])}
        self.grid_cell = cell

    def lookup(self, x: float, y: float):
        """Arc length of the path point nearest (x, y) if (x, y) lies on the path, else None."""
        c = self.grid_cell
        return self.grid.get(grid_key(int(math.floor(x / c)), int(math.floor(y / c))))


def grid_key(ix: int, iy: int) -> int:
    return ix * 1_000_003 + iy


def box_corners(x, y, psi, length, width):
    c, s = math.cos(psi), math.sin(psi)
    hl, hw = 0.5 * length, 0.5 * width
    return [(x + c * hl - s * hw, y + s * hl + c * hw), (x - c * hl - s * hw, y - s * hl + c * hw),
            (x - c * hl + s * hw, y - s * hl - c * hw), (x + c * hl + s * hw, y + s * hl - c * hw)]


def boxes_overlap(x1, y1, psi1, x2, y2, psi2, hl, hw, r2sum) -> bool:
    """Separating-axis test for two equal-size oriented rectangles (half sizes hl, hw),
    after a bounding-circle rejection (r2sum = (2*circumradius)^2)."""
    dx = x2 - x1
    dy = y2 - y1
    if dx * dx + dy * dy > r2sum:
        return False
    c1, s1 = math.cos(psi1), math.sin(psi1)
    c2, s2 = math.cos(psi2), math.sin(psi2)
    C = abs(c1 * c2 + s1 * s2)
    S = abs(s2 * c1 - c2 * s1)
    if abs(dx * c1 + dy * s1) > hl + hl * C + hw * S:
        return False
    if abs(-dx * s1 + dy * c1) > hw + hl * S + hw * C:
        return False
    if abs(dx * c2 + dy * s2) > hl + hl * C + hw * S:
        return False
    if abs(-dx * s2 + dy * c2) > hw + hl * S + hw * C:
        return False
    return True


def polyline_crossings(a, b, merge_tol: float = 0.5):
    """Proper crossing points of two polylines (touching endpoints excluded), with points
    closer than ``merge_tol`` merged. Used for potential-collision-point counts."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    p, r = a[:-1], np.diff(a, axis=0)
    q, s = b[:-1], np.diff(b, axis=0)
    rxs = r[:, None, 0] * s[None, :, 1] - r[:, None, 1] * s[None, :, 0]
    qp = q[None, :, :] - p[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (qp[..., 0] * s[None, :, 1] - qp[..., 1] * s[None, :, 0]) / rxs
        u = (qp[..., 0] * r[:, None, 1] - qp[..., 1] * r[:, None, 0]) / rxs
    eps = 1e-9
    # half-open parameter intervals: a crossing on a vertex is seen once, duplicates merged below
    hit = (np.abs(rxs) > 1e-12) & (t >= -eps) & (t < 1 - eps) & (u >= -eps) & (u < 1 - eps)
    ii, jj = np.nonzero(hit)
    pts = p[ii] + t[ii, jj][:, None] * r[ii]
    # drop crossings at the very ends of either polyline (touching, not crossing)
    ends = np.array([a[0], a[-1], b[0], b[-1]])
    out = []
    for pt in pts:
        if np.min(np.hypot(*(ends - pt).T)) < merge_tol:
            continue
        if all(math.hypot(pt[0] - o[0], pt[1] - o[1]) >= merge_tol for o in out):
            out.append((float(pt[0]), float(pt[1])))
    return out


def point_segment_distances(points, poly, return_segment=False):
    """Distance from every point (N,2) to polyline ``poly`` (M,2): (N,) array (and the
    index of the nearest segment when ``return_segment``)."""
    points = np.asarray(points, float)
    poly = np.asarray(poly, float)
    a, d = poly[:-1], np.diff(poly, axis=0)
    dd = np.maximum(np.sum(d * d, axis=1), 1e-12)
    w = points[:, None, :] - a[None, :, :]
    t = np.clip(np.sum(w * d[None], axis=2) / dd[None], 0.0, 1.0)
    proj = a[None] + t[..., None] * d[None]
    d = np.hypot(points[:, None, 0] - proj[..., 0], points[:, None, 1] - proj[..., 1])
    j = np.argmin(d, axis=1)
    dist = d[np.arange(len(points)), j]
    return (dist, j) if return_segment else dist


class MapFrame:
    """Where a map's own frame (junction centre at the origin, the EV's arm to the south)
    sits in the world's fixed ``map`` frame: translation (x, y) and rotation ``heading``
    (rad, counter-clockwise). The simulator core and the planner work in the map's own
    frame; the ROS boundary (world node, planner node) converts, so a source whose junction
    lies elsewhere needs only a map file with that pose.

    ``states``: rows [x, y, v, psi] (speed unchanged); ``poses``: rows [x, y, psi]."""

    __slots__ = ("x", "y", "heading", "_c", "_s")

    def __init__(self, x: float = 0.0, y: float = 0.0, heading: float = 0.0):
        self.x, self.y, self.heading = float(x), float(y), float(heading)
        self._c, self._s = math.cos(self.heading), math.sin(self.heading)

    @property
    def identity(self) -> bool:
        return self.x == 0.0 and self.y == 0.0 and self.heading == 0.0

    def _move(self, rows, cols, to_world: bool):
        a = np.array(rows, dtype=float, copy=True)
        flat = a.reshape(-1, a.shape[-1]) if a.size else a.reshape(0, len(cols) + 2)
        if self.identity or not flat.size:
            return a
        x, y = flat[:, 0].copy(), flat[:, 1].copy()
        c, s = self._c, self._s
        if to_world:
            flat[:, 0], flat[:, 1] = self.x + c * x - s * y, self.y + s * x + c * y
        else:
            dx, dy = x - self.x, y - self.y
            flat[:, 0], flat[:, 1] = c * dx + s * dy, -s * dx + c * dy
        for k in cols:
            flat[:, k] = [wrap_angle(v + (self.heading if to_world else -self.heading)) for v in flat[:, k]]
        return flat.reshape(a.shape)

    def states_to_world(self, states):
        return self._move(states, (3,), True)

    def states_to_map(self, states):
        return self._move(states, (3,), False)

    def poses_to_world(self, poses):
        return self._move(poses, (2,), True)

    def poses_to_map(self, poses):
        return self._move(poses, (2,), False)
