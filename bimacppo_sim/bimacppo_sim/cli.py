"""bimacppo-sim: render scenarios, run scripted episodes to GIF, render a recording (MCAP) to
GIF, build the reference table of the scripted drivers, and benchmark the world."""
from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
import tracemalloc
from collections import Counter

from bimacppo_common.conventions import TASKS

from .drivers import DRIVERS, run_episode
from .road import DEFAULT_MAP, available_maps, load_map, map_from_yaml
from .world import Scenario, World


def _scenario(a):
    return Scenario(n_sv=a.n_sv, task=a.task, seed=a.seed)


def cmd_render(a):
    from .render import Renderer
    w = World(load_map(a.map))
    w.reset(_scenario(a))
    r = Renderer(w, view=a.view)
    r.save_png(a.output)
    print(f"wrote {a.output}  (n_pcp={w.n_pcp}, styles={w.sv_styles}, manoeuvres={w.sv_maneuvers})")


def cmd_episode(a):
    from .render import Renderer, save_gif
    w = World(load_map(a.map))
    w.reset(_scenario(a))
    r = Renderer(w, view=a.view)
    frames = []
    k = [0]

    def grab(world):
        if k[0] % a.every == 0 or world.done:
            frames.append(r.rgb_array())
        k[0] += 1
    res = run_episode(w, _scenario(a), a.driver, frames=grab)
    save_gif(frames, a.output, w.dt * a.every)
    print(f"{a.driver}: {res.outcome} after {res.time:.1f}s (collided_with={res.collided_with}); wrote {a.output}")


def output_path(output: str, source: str, overwrite: bool) -> str:
    """Where render-bag may write: a .gif in an existing directory; an existing file only with
    ``overwrite``, and never the recording itself."""
    if not output.lower().endswith(".gif"):
        raise ValueError(f"output must be a .gif file, got {output!r}")
    folder = os.path.dirname(os.path.abspath(output))
    if not os.path.isdir(folder):
        raise ValueError(f"output directory does not exist: {folder}")
    if os.path.isdir(output):
        raise ValueError(f"{output} is a directory")
    if os.path.exists(output):
        if os.path.exists(source) and os.path.samefile(output, source):
            raise ValueError(f"{output} is the recording itself: refusing to overwrite it")
        if not overwrite:
            raise ValueError(f"{output} exists: refusing to overwrite it (pass --overwrite, or name a new file)")
    return output


def _frame_dt(frames, fallback: float) -> float:
    """Seconds between consecutive states of the recording (median; the source's own dt)."""
    import numpy as np
    d = np.diff([f.stamp_ns for f in frames]) / 1e9
    d = d[d > 0]
    return float(np.median(d)) if len(d) else fallback


def _in_map_frame(frame, f):
    """A recorded frame's EV, SVs, goal and route in the map's own frame (where the Renderer draws
    the road): a map file's pose places that frame in the fixed ``map`` frame the messages use."""
    import numpy as np
    route = None
    if f.route is not None:
        route = frame.poses_to_map(np.c_[f.route[:, :2], np.zeros(len(f.route))])[:, :2]
    goal = None if f.goal is None else frame.poses_to_map(f.goal)
    return frame.states_to_map(f.ego), frame.states_to_map(f.svs), goal, route


def recorded_map(bag, source: str):
    """The road a recording names (our recorder's ``map_id``, read from the bag) and its name: the
    recorded text of a map file first (what the world ran on, also where the file is absent or
    changed since), else the id or path loaded here; a bag without a map, and one whose map cannot
    be loaded here (one ``warning:`` line), are drawn on DEFAULT_MAP."""
    if bag.map_id:
        try:
            if bag.map_yaml:
                return map_from_yaml(bag.map_yaml, f"{bag.map_id} (as recorded in {source})"), bag.map_id
            return load_map(bag.map_id), bag.map_id
        except Exception as exc:  # noqa: BLE001 - any fault of a recorded map file: fall back, say why
            why = (str(exc).splitlines() or [type(exc).__name__])[0]
            print(f"warning: {source} was recorded on map {bag.map_id!r}, which cannot be loaded here ({why}); "
                  f"drawing it on {DEFAULT_MAP} (name its map with --map)", file=sys.stderr)
    return load_map(DEFAULT_MAP), DEFAULT_MAP


def cmd_render_bag(a):
    from tqdm import tqdm

    from .config import WorldConfig
    from .render import FrameView, GifWriter, Renderer
    try:   # the message types of the recording: only this command needs ROS
        from bimacppo_bag.bag_frames import read_bag
    except ImportError as exc:
        raise ValueError(f"render-bag needs the ROS 2 Python packages (rclpy, common_interfaces): {exc}") from None
    if a.every < 1 or a.max_frames < 1:
        raise ValueError(f"--every and --max-frames must be >= 1, got {a.every} and {a.max_frames}")
    output = a.output or os.path.splitext(os.path.basename(os.path.normpath(a.bag)))[0] + ".gif"
    output = output_path(output, a.bag, a.overwrite)
    cfg = WorldConfig.load()
    road, map_name = (load_map(a.map), a.map) if a.map is not None else (None, "")   # a bad --map: before reading
    with tqdm(desc="reading", unit=" msg", disable=None, leave=False) as bar:
        bag = read_bag(a.bag, progress=bar.update)
    if road is None:
        road, map_name = recorded_map(bag, a.bag)
    for topic, why in sorted(bag.skipped.items()):
        print(f"warning: {topic}: skipped ({why})", file=sys.stderr)
    if bag.damaged:
        print(f"warning: {a.bag} is damaged, rendering what was readable: {bag.damaged}", file=sys.stderr)
    frames = bag.frames
    every = max(a.every, math.ceil(len(frames) / a.max_frames))
    if every > a.every:
        print(f"note: {len(frames)} states; drawing one in {every} to stay within --max-frames {a.max_frames}")
    keep = [f for i, f in enumerate(frames) if i % every == 0 or f.outcome is not None]
    folder = os.path.dirname(os.path.abspath(output))
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(output)}.", suffix=".part", dir=folder)
    except OSError as exc:
        raise ValueError(f"cannot write in {folder}: {exc.strerror}") from None
    os.close(fd)
    gif = GifWriter(tmp, _frame_dt(frames, cfg.dt) * every)
    view = FrameView(road, cfg)
    r = Renderer(view, view=a.view)
    try:   # the GIF appears complete or not at all: an existing file is replaced only at the end
        for f in tqdm(keep, desc="rendering", unit=" frame", disable=None, leave=False):
            view.show(*_in_map_frame(road.frame, f), time=f.time_s, task=f.task, outcome=f.outcome)
            gif.append(r.rgb_array(x_imr=None if f.x_imr is None else road.frame.states_to_map(f.x_imr)))
        gif.close()
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)   # mkstemp makes it private; the GIF gets a new file's mode
        os.replace(tmp, output)
    finally:
        r.close()
        if os.path.exists(tmp):
            os.unlink(tmp)
    outcomes = Counter(f.outcome for f in frames if f.outcome)
    ends = ", ".join(f"{k}: {v}" for k, v in sorted(outcomes.items())) or "no episode result"
    print(f"{len(keep)} frames of {len(frames)} states ({ends}) on map {map_name}; wrote {output}")


def reference_table(map_id, episodes, seed0, drivers=DRIVERS, progress=True):
    from tqdm import tqdm
    road = load_map(map_id)
    w = World(road)
    rows = []
    combos = [(d, t, n) for d in drivers for t in TASKS if t in road.turns for n in range(road.max_sv + 1)]
    bar = tqdm(total=len(combos) * episodes, disable=not progress, desc="reference")
    for d, t, n in combos:
        c = Counter()
        steps = 0
        for e in range(episodes):
            res = run_episode(w, Scenario(n, t, seed0 + e), d)
            c[res.outcome] += 1
            steps += res.steps
            bar.update()
        rows.append((d, t, n, c["success"], c["collision"], c["timeout"], steps / episodes * w.dt))
    bar.close()
    return rows


def cmd_reference(a):
    rows = reference_table(a.map, a.episodes, a.seed0)
    lines = [f"Map `{a.map}`, {a.episodes} episodes per cell, seeds {a.seed0}..{a.seed0 + a.episodes - 1}.", "",
             "| driver | task | N_sv | success % | collision % | timeout % | mean episode time (s) |",
             "|---|---|---|---|---|---|---|"]
    for d, t, n, s, c, to, mt in rows:
        k = a.episodes / 100.0
        lines.append(f"| {d} | {t} | {n} | {s / k:.0f} | {c / k:.0f} | {to / k:.0f} | {mt:.1f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(text)
        print(f"wrote {a.out}")


def bench(map_id=DEFAULT_MAP, n_sv=3, steps=20000, seed0=0):
    """World steps/s with n_sv SVs; the EV input is a constant (controller excluded)."""
    import numpy as np
    w = World(load_map(map_id))
    action = np.array([0.5, 0.0])
    done_steps, eps = 0, 0
    tracemalloc.start()
    t0 = time.perf_counter()
    while done_steps < steps:
        w.reset(Scenario(n_sv, "straight", seed0 + eps))
        eps += 1
        while True:
            done_steps += 1
            if w.step(action).done or done_steps >= steps:
                break
    dt = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    # second pass without tracemalloc (it slows allocation-heavy code)
    done_steps2, eps2 = 0, 0
    t0 = time.perf_counter()
    while done_steps2 < steps:
        w.reset(Scenario(n_sv, "straight", seed0 + eps2))
        eps2 += 1
        while True:
            done_steps2 += 1
            if w.step(action).done or done_steps2 >= steps:
                break
    dt2 = time.perf_counter() - t0
    import resource
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {"steps": done_steps2, "episodes": eps2, "seconds": dt2, "steps_per_s": done_steps2 / dt2,
            "steps_per_s_traced": done_steps / dt, "tracemalloc_peak_kib": peak / 1024.0, "max_rss_mib": rss}


def cmd_bench(a):
    r = bench(a.map, a.n_sv, a.steps)
    for k, v in r.items():
        print(f"{k}: {v:.1f}" if isinstance(v, float) else f"{k}: {v}")


def build_parser():
    p = argparse.ArgumentParser(prog="bimacppo-sim", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)

    def common(sp):
        sp.add_argument("--map", default=DEFAULT_MAP, help=f"map id {available_maps()} or a YAML path")
        sp.add_argument("--n-sv", type=int, default=3, help="number of SVs (0..map max)")
        sp.add_argument("--task", default="left", choices=TASKS, help="EV task")
        sp.add_argument("--seed", type=int, default=0, help="scenario seed (>= 0)")
        sp.add_argument("--view", type=float, default=60.0, help="half-width of the view (m)")
    sp = sub.add_parser("render", help="draw the initial state of a scenario to PNG")
    common(sp)
    sp.add_argument("-o", "--output", default="scenario.png")
    sp.set_defaults(func=cmd_render)
    sp = sub.add_parser("episode", help="run a scripted driver and write the episode as GIF")
    common(sp)
    sp.add_argument("--driver", default="go", choices=DRIVERS)
    sp.add_argument("--every", type=int, default=2, help="keep every k-th frame")
    sp.add_argument("-o", "--output", default="episode.gif")
    sp.set_defaults(func=cmd_episode)
    sp = sub.add_parser("render-bag", help="draw a recording (MCAP file or rosbag2 directory) as GIF")
    sp.add_argument("bag", help="MCAP file or rosbag2 directory (any ROS 2 writer)")
    sp.add_argument("-o", "--output", default="", help="GIF path (default: the bag's name with .gif, here)")
    sp.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    sp.add_argument("--map", default=None, help=f"map the recording ran on {available_maps()} or a YAML path "
                    f"(default: the map our recorder stored in the bag, else {DEFAULT_MAP})")
    sp.add_argument("--view", type=float, default=60.0, help="half-width of the view (m)")
    sp.add_argument("--every", type=int, default=2, help="keep every k-th state (>= 1)")
    sp.add_argument("--max-frames", type=int, default=1000,
                    help="at most this many frames: a longer recording keeps fewer states")
    sp.set_defaults(func=cmd_render_bag)
    sp = sub.add_parser("reference", help="success/collision/timeout table of the scripted drivers")
    sp.add_argument("--map", default=DEFAULT_MAP)
    sp.add_argument("--episodes", type=int, default=100)
    sp.add_argument("--seed0", type=int, default=10000, help="first seed; cell uses seed0..seed0+episodes-1")
    sp.add_argument("--out", default=None, help="write the markdown table here")
    sp.set_defaults(func=cmd_reference)
    sp = sub.add_parser("bench", help="world steps/s and peak memory (controller excluded)")
    sp.add_argument("--map", default=DEFAULT_MAP)
    sp.add_argument("--n-sv", type=int, default=3)
    sp.add_argument("--steps", type=int, default=20000)
    sp.set_defaults(func=cmd_bench)
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except ValueError as exc:
        print(f"bimacppo-sim: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("bimacppo-sim: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
