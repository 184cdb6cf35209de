"""Bird's-eye rendering with matplotlib (Agg): PNG files, RGB arrays, GIF episodes.

The road is drawn once per Renderer (static background); each frame only moves the
vehicle polygons, so rgb_array rendering for gymnasium stays cheap-ish. The Renderer draws a
World, or a :class:`FrameView`: states that come from elsewhere (a recording) on a map.
"""
from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, Polygon, Rectangle  # noqa: E402

from .geometry import box_corners  # noqa: E402

STYLE_COLOURS = {"aggressive": "#d62728", "moderate": "#ff7f0e", "conservative": "#1f77b4"}
SV_COLOUR = "#17becf"       # an SV whose driver style is unknown (e.g. read from a recording)
EV_COLOUR = "#2ca02c"
ROAD, GRASS, MARK = "#5a5a5a", "#cfe3c0", "#f0f0f0"


class Renderer:
    def __init__(self, world, view: float = 45.0, size_px: int = 480):
        self.world = world
        road = world.road
        self.fig = plt.figure(figsize=(size_px / 100, size_px / 100), dpi=100)
        self.ax = self.fig.add_axes([0, 0, 1, 1])
        ax = self.ax
        ax.set_facecolor(GRASS)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        self._draw_road(road)
        self.view = view
        self._dyn = []

    def _draw_road(self, road):
        ax = self.ax
        W, hw = road.lane_width, road.half_road
        if road.kind == "straight":
            L = road.length
            ax.add_patch(Rectangle((-hw, -L / 2), 2 * hw, L, color=ROAD, zorder=0))
            for k in range(1, road.n_lanes):
                x = -hw + k * W
                ax.plot([x, x], [-L / 2, L / 2], color=MARK, lw=1, ls=(0, (4, 4)), zorder=1)
            return
        H, ext, rc = road.H, road.H + road.arm_length, road.corner_radius
        ax.add_patch(Rectangle((-hw, -ext), 2 * hw, 2 * ext, color=ROAD, zorder=0))
        ax.add_patch(Rectangle((-ext, -hw), 2 * ext, 2 * hw, color=ROAD, zorder=0))
        ax.add_patch(Rectangle((-H, -H), 2 * H, 2 * H, color=ROAD, zorder=0))
        for sx in (-1, 1):
            for sy in (-1, 1):
                ax.add_patch(Circle((sx * H, sy * H), rc, color=GRASS, zorder=0.5))
        for ln in road.lanes.values():
            if ln.kind == "conn":
                ax.plot(ln.points[:, 0], ln.points[:, 1], color="#7a7a7a", lw=0.5, zorder=1)
        for arm_dir in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            d = np.array(arm_dir, float)
            r = np.array([d[1], -d[0]])
            for k in range(-road.n_lanes + 1, road.n_lanes):
                off = k * W * r
                a, b = d * H + off, d * ext + off
                style = "-" if k == 0 else (0, (4, 4))
                ax.plot([a[0], b[0]], [a[1], b[1]], color="#e8c33a" if k == 0 else MARK, lw=1, ls=style, zorder=1)

    def draw(self, x_imr=None, show_route: bool = True, candidates=None):
        """Update the dynamic layer; returns the figure. ``candidates`` (K, 3) are the planner's
        A1 waypoints (drawn as open circles), ``x_imr`` the chosen reference (cross + heading)."""
        for art in self._dyn:
            art.remove()
        self._dyn = []
        w, ax = self.world, self.ax
        veh = w.cfg.vehicle
        if show_route and w.route is not None:
            self._dyn += ax.plot(w.route[:, 0], w.route[:, 1], ".", color="#9467bd", ms=3, zorder=2)
        if w.goal is not None:
            self._dyn.append(ax.scatter([w.goal[0]], [w.goal[1]], marker="*", s=160, color="gold",
                                        edgecolors="k", zorder=3))
        for st, style, active in zip(w.sv_states(), w.sv_styles, w.sv_active):
            if active:
                self._dyn.append(ax.add_patch(Polygon(box_corners(st[0], st[1], st[3], veh.length, veh.width),
                                                      color=STYLE_COLOURS.get(style, SV_COLOUR), zorder=4)))
        ex, ey, ev, epsi = w.ego_tuple()
        if w.scenario is not None and w.scenario.ev_present:
            self._dyn.append(ax.add_patch(Polygon(box_corners(ex, ey, epsi, veh.length, veh.width),
                                                  color=EV_COLOUR, ec="k", zorder=5)))
        if candidates is not None and len(candidates):
            c = np.asarray(candidates, float)
            self._dyn.append(ax.scatter(c[:, 0], c[:, 1], marker="o", s=40, facecolors="none",
                                        edgecolors="magenta", linewidths=1.0, zorder=6))
        if x_imr is not None:
            xi = np.asarray(x_imr, float)
            self._dyn.append(ax.scatter([xi[0]], [xi[1]], marker="x", s=80, color="magenta", zorder=6))
            if len(xi) >= 3:
                self._dyn.append(ax.arrow(xi[0], xi[1], 2 * math.cos(xi[-1]), 2 * math.sin(xi[-1]),
                                          color="magenta", width=0.15, zorder=6))
        cx, cy = (0.0, 0.0) if w.road.kind == "four_way" else (0.0, ey + 20.0)
        ax.set_xlim(cx - self.view, cx + self.view)
        ax.set_ylim(cy - self.view, cy + self.view)
        txt = f"t={w.time:.1f}s  v={ev:.1f}m/s  {w.scenario.task if w.scenario else ''}"
        if w.outcome:
            txt += f"  {w.outcome}"
        self._dyn.append(ax.text(0.02, 0.97, txt, transform=ax.transAxes, va="top", fontsize=9,
                                 bbox=dict(fc="white", alpha=0.7), zorder=7))
        return self.fig

    def rgb_array(self, **kw) -> np.ndarray:
        self.draw(**kw)
        self.fig.canvas.draw()
        return np.asarray(self.fig.canvas.buffer_rgba())[..., :3].copy()

    def save_png(self, path, **kw):
        self.draw(**kw)
        self.fig.savefig(path)

    def close(self):
        plt.close(self.fig)


class FrameView:
    """The part of a World that :class:`Renderer` draws, set from outside (one state at a time).

    ``road`` and ``cfg`` (vehicle bodies) are a map's and a WorldConfig's; :meth:`show` sets the
    EV ``[x, y, v, psi]``, the SVs ``(n, 4)`` (style unknown: drawn in ``SV_COLOUR``, all active),
    goal ``[x, y, psi]`` or None, route ``(M, >= 2)`` or None, the episode time, task and outcome.
    """

    class _Scenario:
        ev_present = True

        def __init__(self, task: str):
            self.task = task

    def __init__(self, road, cfg):
        self.road, self.cfg = road, cfg
        self.show(np.zeros(4))

    def show(self, ego, svs=None, goal=None, route=None, time: float = 0.0, task: str = "",
             outcome=None) -> "FrameView":
        self._ego = tuple(float(c) for c in np.asarray(ego, float).reshape(4))
        self._svs = np.zeros((0, 4)) if svs is None else np.asarray(svs, float).reshape(-1, 4)
        self.goal = None if goal is None else np.asarray(goal, float)
        self.route = None if route is None or len(route) < 2 else np.asarray(route, float)
        self.time, self.outcome, self.scenario = float(time), outcome, self._Scenario(task)
        return self

    def ego_tuple(self):
        return self._ego

    def sv_states(self) -> np.ndarray:
        return self._svs

    @property
    def sv_styles(self):
        return [None] * len(self._svs)

    @property
    def sv_active(self):
        return [True] * len(self._svs)


def render_rgb(world, **kw) -> np.ndarray:
    """One-off RGB frame (H, W, 3) uint8 of the world's current state."""
    r = Renderer(world)
    try:
        return r.rgb_array(**kw)
    finally:
        r.close()


class GifWriter:
    """An animated GIF built one RGB frame at a time, each shown ``dt`` seconds, looping.

    Frames are palette-quantised as they arrive (a GIF holds 256 colours per frame anyway), so
    a long animation keeps a third of its RGB size in memory until :meth:`close` writes the file.
    GIF stores frame durations in milliseconds (rounded to 10 ms by most players).
    """

    def __init__(self, path, dt: float):
        if not dt > 0:
            raise ValueError(f"GIF frame duration must be > 0 s, got {dt}")
        self.path, self.duration_ms = path, int(round(1000.0 * dt))
        self._frames = []

    def append(self, rgb) -> None:
        from PIL import Image
        self._frames.append(Image.fromarray(np.asarray(rgb, dtype=np.uint8)).quantize(colors=256))

    def __len__(self) -> int:
        return len(self._frames)

    def close(self) -> None:
        if not self._frames:
            raise ValueError(f"no frames to write to {self.path}")
        first, *rest = self._frames
        first.save(self.path, format="GIF", save_all=True, append_images=rest, duration=self.duration_ms,
                   loop=0)
        self._frames = []


def save_gif(frames, path, dt: float):
    w = GifWriter(path, dt)
    for f in frames:
        w.append(f)
    w.close()
