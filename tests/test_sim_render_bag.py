"""bimacppo-sim render-bag: a recording drawn as the bird's-eye GIF of ``bimacppo-sim episode``.

The bags are written here with mcap_ros2's writer (not our recorder) from real World episodes,
each message built by the converters of interfaces.py; bad inputs give one error line and exit
2, and an existing output survives unless --overwrite. Without --map a bag is drawn on the map
its ``bimacppo`` metadata record names (what our recorder writes: tests/test_ros_mcap.py), a bag
without one on dual_lane_4way.
"""
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")
from mcap_ros2.writer import Writer as Ros2Writer  # noqa: E402
from PIL import Image  # noqa: E402

from bimacppo_sim import Scenario, World, load_map  # noqa: E402
from bimacppo_sim.cli import main  # noqa: E402
from bimacppo_sim.drivers import run_episode  # noqa: E402
from bimacppo_sim.render import EV_COLOUR  # noqa: E402
from bimacppo_interfaces import contract as I  # noqa: E402
from bimacppo_bag import mcap_io  # noqa: E402

MAP = "single_lane_4way"
EPISODES = (Scenario(1, "straight", 3), Scenario(0, "left", 4))


def _plain(msg):
    """An rclpy message as nested dicts and lists (what mcap_ros2's encoder takes)."""
    if hasattr(msg, "get_fields_and_field_types"):
        return {name: _plain(getattr(msg, name)) for name in msg.get_fields_and_field_types()}
    if isinstance(msg, (list, tuple)) or hasattr(msg, "tolist"):
        return [_plain(v) for v in (msg.tolist() if hasattr(msg, "tolist") else msg)]
    if isinstance(msg, bytes) and len(msg) == 1:   # rclpy's ``byte`` fields (DiagnosticStatus.level)
        return msg[0]
    return msg


def _write_bag(path, with_topics=tuple(I.TOPIC_TYPES), chunk_size=1024 * 1024, odom_type=None, odom_frame=None,
               map_id=MAP, run_metadata=None):
    """Episodes of a World driven by the 'go' driver, published as the world node does (in the
    fixed map frame: moved by the map file's pose, if any), with ``run_metadata`` as the
    recorder's ``bimacppo`` metadata record if given; returns (stamps of the states, outcomes, EV
    states in the map's own frame)."""
    w = World(load_map(map_id))
    fr = w.road.frame
    stamps, outcomes, egos = [], [], []
    k = [0]
    with open(path, "wb") as f:
        bag = Ros2Writer(f, chunk_size=chunk_size)
        if run_metadata is not None:
            bag.add_metadata(mcap_io.RUN_METADATA, run_metadata)
        schemas = {}

        def put(topic, msg, stamp):
            if topic not in with_topics:
                return
            type_name = odom_type if (topic == I.TOPIC_EGO_ODOM and odom_type) else I.TOPIC_TYPES[topic]
            if type_name not in schemas:
                schemas[type_name] = bag.register_msgdef(type_name, mcap_io.full_definition(type_name))
            bag.write_message(topic, schemas[type_name], _plain(msg), log_time=stamp, publish_time=stamp)

        def tick(world):
            k[0] += 1
            stamp = k[0] * 100_000_000
            ego = world.ego
            if len(stamps) == 0 or world.time == 0.0:
                put(I.TOPIC_GOAL, I.goal_to_pose(fr.poses_to_world(world.goal), stamp), stamp)
            odom = I.state_to_odometry(fr.states_to_world(ego), stamp)
            if odom_frame:
                odom.header.frame_id = odom_frame
            if odom_type:
                from std_msgs.msg import String
                odom = String(data="not an odometry")
            put(I.TOPIC_EGO_ODOM, odom, stamp)
            if len(stamps) % 7 == 0:   # a lockstep re-send: the same state twice
                put(I.TOPIC_EGO_ODOM, odom, stamp)
            svs = fr.states_to_world(world.sv_states())
            put(I.TOPIC_OBJECTS, I.svs_to_objects([f"sv{i}" for i in range(len(svs))], svs, stamp), stamp)
            put(I.TOPIC_MARKERS, I.world_markers(fr.states_to_world(ego), svs, fr.poses_to_world(world.goal),
                                                 fr.poses_to_world(world.route), stamp), stamp)
            x_imr = ego + np.array([2.0 * np.cos(ego[3]), 2.0 * np.sin(ego[3]), 0.5, 0.0])
            put(I.TOPIC_REFERENCE, I.reference_to_odometry(fr.states_to_world(x_imr), stamp), stamp)
            stamps.append(stamp)
            egos.append(ego)

        for sc in EPISODES:
            res = run_episode(w, sc, "go", frames=tick)
            outcomes.append(res.outcome)
            st = I.result_to_status(I.EpisodeResult(res.outcome, None, sc.n_sv, sc.task, sc.seed, res.steps,
                                                    stamps[-1]))
            put(I.TOPIC_RESULT, st, stamps[-1])
            k[0] += 1   # a reset advances one tick
        bag.finish()
    return stamps, outcomes, np.array(egos)


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("bag") / "run.mcap"
    stamps, outcomes, egos = _write_bag(path)
    return path, stamps, outcomes, egos


def _gif(path):
    im = Image.open(path)
    frames = []
    for i in range(im.n_frames):
        im.seek(i)
        frames.append((np.asarray(im.convert("RGB")), im.info.get("duration")))
    return frames


def _ev_centre(rgb):
    """Pixel centroid (row, col) of the EV's colour."""
    target = np.array([int(EV_COLOUR[i:i + 2], 16) for i in (1, 3, 5)])
    rows, cols = np.nonzero(np.abs(rgb.astype(int) - target).sum(axis=2) < 30)
    assert len(rows), "EV not drawn"
    return rows.mean(), cols.mean()


def _errors(capsys):
    err = capsys.readouterr().err
    return [ln for ln in err.splitlines() if "error:" in ln], err


def test_render_bag_draws_every_other_state_of_each_episode(bag, tmp_path, capsys):
    path, stamps, outcomes, egos = bag
    out = tmp_path / "run.gif"
    assert main(["render-bag", str(path), "-o", str(out), "--map", MAP, "--every", "2"]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}" in printed and all(o in printed for o in outcomes)
    frames = _gif(out)
    # one frame per distinct state (re-sends drawn once), every 2nd, plus each episode's terminal state
    ends = [i for i, s in enumerate(stamps) if i + 1 == len(stamps) or stamps[i + 1] - s > 100_000_000]
    assert len(ends) == len(EPISODES)
    assert len(frames) == len(range(0, len(stamps), 2)) + len([i for i in ends if i % 2])
    assert {d for _, d in frames} == {200}            # dt of the recording (0.1 s) x 2, in ms
    first, last = _ev_centre(frames[0][0]), _ev_centre(frames[len(range(0, ends[0] + 1, 2)) - 1][0])
    # episode 1 drives north (straight from the south arm): up the image, as the recording says
    assert egos[ends[0], 1] > egos[0, 1] + 10
    assert last[0] < first[0] - 20
    assert not np.array_equal(frames[0][0], frames[1][0])
    import os
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~umask     # a new file's mode, not the temp file's


def test_render_bag_without_reference_and_markers_still_draws_states(tmp_path, capsys):
    path = tmp_path / "states.mcap"
    stamps, _, _ = _write_bag(path, with_topics=(I.TOPIC_EGO_ODOM, I.TOPIC_OBJECTS))
    full = tmp_path / "full.mcap"
    _write_bag(full)
    a, b = tmp_path / "a.gif", tmp_path / "b.gif"
    assert main(["render-bag", str(path), "-o", str(a), "--map", MAP, "--every", "5"]) == 0
    assert main(["render-bag", str(full), "-o", str(b), "--map", MAP, "--every", "5"]) == 0
    fa, fb = _gif(a), _gif(b)
    assert len(fa) == len(range(0, len(stamps), 5))     # no results: no terminal frames added
    assert "no episode result" in capsys.readouterr().out
    # the same states; goal, route and x_IMR only where the bag has them
    assert not np.array_equal(fa[3][0], fb[3][0])
    # (x_IMR, drawn over the EV in one of them, hides a few of its pixels: 4 px = 1 m)
    assert _ev_centre(fa[3][0]) == pytest.approx(_ev_centre(fb[3][0]), abs=3.0)


def test_max_frames_thins_a_long_recording(bag, tmp_path, capsys):
    path, stamps, outcomes, _ = bag
    out = tmp_path / "short.gif"
    assert main(["render-bag", str(path), "-o", str(out), "--map", MAP, "--max-frames", "10"]) == 0
    printed = capsys.readouterr().out
    every = -(-len(stamps) // 10)
    assert f"one in {every} " in printed
    frames = _gif(out)
    assert 10 <= len(frames) <= 10 + len(outcomes)
    assert {d for _, d in frames} == {100 * every}


def test_existing_output_is_kept_unless_overwrite(bag, tmp_path, capsys):
    path = bag[0]
    out = tmp_path / "run.gif"
    out.write_bytes(b"precious")
    assert main(["render-bag", str(path), "-o", str(out), "--map", MAP]) == 2
    errors, err = _errors(capsys)
    assert len(errors) == 1 and "exists" in errors[0] and "--overwrite" in errors[0] and "Traceback" not in err
    assert out.read_bytes() == b"precious"
    assert main(["render-bag", str(path), "-o", str(out), "--map", MAP, "--every", "20", "--overwrite"]) == 0
    assert len(_gif(out)) >= 2
    assert not list(tmp_path.glob(".run.gif.*"))      # no temporary file left behind
    # the recording itself is never the output, --overwrite or not
    gif_named_bag = tmp_path / "bag.gif"
    gif_named_bag.write_bytes(path.read_bytes())
    assert main(["render-bag", str(gif_named_bag), "-o", str(gif_named_bag), "--overwrite", "--map", MAP]) == 2
    errors, _ = _errors(capsys)
    assert len(errors) == 1 and "recording itself" in errors[0]
    assert gif_named_bag.read_bytes() == path.read_bytes()


@pytest.mark.parametrize("case", ["missing", "garbage", "no_odom", "wrong_type", "bad_frame", "not_gif", "no_dir",
                                  "read_only_dir"])
def test_bad_inputs_are_one_error_line(case, bag, tmp_path, capsys):
    src, out = tmp_path / "x.mcap", tmp_path / "x.gif"
    want = {"missing": "no such file", "garbage": "not a readable MCAP", "no_odom": "/ego/odom",
            "wrong_type": "std_msgs/msg/String", "bad_frame": "rejected by the converters", "not_gif": ".gif",
            "no_dir": "does not exist", "read_only_dir": "cannot write in"}[case]
    if case == "garbage":
        src.write_bytes(np.random.default_rng(0).bytes(4096))
    elif case == "no_odom":
        _write_bag(src, with_topics=(I.TOPIC_GOAL, I.TOPIC_OBJECTS))
    elif case == "wrong_type":
        _write_bag(src, odom_type="std_msgs/msg/String")
    elif case == "bad_frame":
        _write_bag(src, odom_frame="odom")
    elif case in ("not_gif", "no_dir", "read_only_dir"):
        src = bag[0]
        # /sys refuses new files even to root (a read-only directory would not stop root)
        out = {"not_gif": tmp_path / "x.png", "no_dir": tmp_path / "nowhere" / "x.gif",
               "read_only_dir": Path("/sys/bimacppo_render_bag_test.gif")}[case]
    assert main(["render-bag", str(src), "-o", str(out), "--map", MAP]) == 2
    errors, err = _errors(capsys)
    assert len(errors) == 1 and want in errors[0], err
    assert "Traceback" not in err and not out.exists()
    if case == "no_odom":
        assert I.TOPIC_GOAL in errors[0]      # says what the bag holds instead


def _damage_middle_chunk(src, dst):
    from mcap.reader import make_reader
    data = bytearray(src.read_bytes())
    with open(src, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    ci = chunks[len(chunks) // 2]
    records_at = ci.chunk_start_offset + 9 + 8 + 8 + 8 + 4 + 4 + len(ci.compression) + 8
    for i in range(ci.compressed_size // 3, ci.compressed_size // 3 + 6):
        data[records_at + i] ^= 0x5A
    dst.write_bytes(bytes(data))


def test_damaged_chunk_renders_the_rest_with_a_warning(tmp_path, capsys):
    good, bad = tmp_path / "good.mcap", tmp_path / "bad.mcap"
    _write_bag(good, chunk_size=16 * 1024)
    _damage_middle_chunk(good, bad)
    a, b = tmp_path / "good.gif", tmp_path / "bad.gif"
    assert main(["render-bag", str(good), "-o", str(a), "--map", MAP, "--every", "1"]) == 0
    capsys.readouterr()
    assert main(["render-bag", str(bad), "-o", str(b), "--map", MAP, "--every", "1"]) == 0
    err = capsys.readouterr().err
    assert "warning:" in err and "damaged" in err and "Traceback" not in err
    assert 0 < len(_gif(b)) < len(_gif(a))


def test_rosbag2_directory_renders_its_files(bag, tmp_path, capsys):
    import shutil

    import yaml
    path, stamps, _, _ = bag
    d = tmp_path / "run_bag"
    d.mkdir()
    shutil.copy(path, d / "run_0.mcap")
    (d / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": {
        "version": 9, "storage_identifier": "mcap", "relative_file_paths": ["run_0.mcap"]}}))
    out = tmp_path / "dir.gif"
    assert main(["render-bag", str(d), "-o", str(out), "--map", MAP, "--every", "10"]) == 0
    assert f"of {len(stamps)} states" in capsys.readouterr().out
    assert len(_gif(out)) >= len(range(0, len(stamps), 10))


def test_route_from_markers_takes_the_worlds_route_only():
    from bimacppo_interfaces.contract import route_from_markers
    route = np.array([[0.0, -50.0, 1.57], [0.0, -10.0, 1.57], [3.0, 2.0, 0.5]])
    markers = I.world_markers([0, -50, 5, 1.57], np.zeros((2, 4)), [3, 2, 0.5], route, 100).markers
    assert route_from_markers(markers).tolist() == route[:, :2].tolist()
    assert route_from_markers(I.world_markers([0, 0, 0, 0], [], None, None, 100).markers) is None
    assert route_from_markers(I.reference_markers([0, 0, 1, 0], 100).markers) is None


def test_progress_bars_on_a_terminal_only(bag, tmp_path):
    """On a terminal, reading and rendering show tqdm bars on stderr; piped, stderr stays quiet."""
    import fcntl
    import os
    import pty
    import select
    import struct
    import subprocess
    import sys
    import termios

    cmd = [sys.executable, "-m", "bimacppo_sim.cli", "render-bag", str(bag[0]), "--map", MAP, "--every", "10"]
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))   # a sized terminal
    proc = subprocess.Popen([*cmd, "-o", str(tmp_path / "tty.gif")], stderr=slave, stdout=subprocess.PIPE)
    os.close(slave)
    shown = b""
    while True:
        ready, _, _ = select.select([master], [], [], 0.5)
        if ready:
            try:
                data = os.read(master, 65536)
            except OSError:   # the child closed its end
                break
            if not data:
                break
            shown += data
        elif proc.poll() is not None:
            break
    assert proc.wait(timeout=120) == 0
    os.close(master)
    assert b"rendering:" in shown and b"frame/s" in shown, shown[-500:]
    piped = subprocess.run([*cmd, "-o", str(tmp_path / "pipe.gif")], capture_output=True, text=True, timeout=120)
    assert piped.returncode == 0 and "rendering" not in piped.stderr, piped.stderr


def _render(bag_path, out, *args):
    """render-bag with few frames (the caller reads what it printed); returns the GIF's frames."""
    assert main(["render-bag", str(bag_path), "-o", str(out), "--max-frames", "3", "--overwrite", *args]) == 0
    return _gif(out)


def _same(a, b):
    return len(a) == len(b) and all(np.array_equal(x, y) for (x, _), (y, _) in zip(a, b))


def test_without_map_the_bag_draws_the_map_it_records(bag, tmp_path, capsys):
    """A bag that names its map (single_lane_4way) is drawn on that road without --map; one
    without the record (another writer's) on dual_lane_4way, as before; --map always wins."""
    named = tmp_path / "named.mcap"
    _write_bag(named, run_metadata={mcap_io.MAP_ID_KEY: MAP})
    out = tmp_path / "x.gif"
    recorded = _render(named, out)
    assert f"on map {MAP};" in capsys.readouterr().out
    assert _same(recorded, _render(named, out, "--map", MAP))
    default = _render(named, out, "--map", "dual_lane_4way")
    assert not _same(recorded, default)                       # the roads differ: the flag is not a no-op
    # the module's bag (mcap_ros2 writer, no record): dual_lane_4way, no warning
    capsys.readouterr()
    unnamed = _render(bag[0], out)
    printed = capsys.readouterr()
    assert "on map dual_lane_4way;" in printed.out and "warning" not in printed.err, printed
    assert _same(unnamed, _render(bag[0], out, "--map", "dual_lane_4way"))


def test_the_map_record_is_read_from_a_killed_recording_too(bag, tmp_path):
    """No summary (a killed recorder): the record is found by the scan, as the messages are."""
    from bimacppo_bag.bag_frames import read_bag
    full, cut = tmp_path / "full.mcap", tmp_path / "cut.mcap"
    _write_bag(full, chunk_size=16 * 1024, run_metadata={mcap_io.MAP_ID_KEY: MAP, mcap_io.MAP_YAML_KEY: "id: x"})
    cut.write_bytes(full.read_bytes()[: full.stat().st_size * 2 // 3])
    for path in (full, cut):
        frames = read_bag(path)
        assert (frames.map_id, frames.map_yaml) == (MAP, "id: x"), path
    assert read_bag(cut).damaged and not read_bag(full).damaged
    assert (read_bag(bag[0]).map_id, read_bag(bag[0]).map_yaml) == ("", "")


@pytest.mark.parametrize("recorded", ["no_such_map", "gone/junction.yaml"])
def test_a_recorded_map_not_loadable_here_is_one_warning(recorded, bag, tmp_path, capsys):
    path = tmp_path / "elsewhere.mcap"
    _write_bag(path, run_metadata={mcap_io.MAP_ID_KEY: recorded})
    out = tmp_path / "x.gif"
    frames = _render(path, out)
    printed = capsys.readouterr()
    warnings = [ln for ln in printed.err.splitlines() if "warning:" in ln]
    assert len(warnings) == 1 and repr(recorded) in warnings[0] and "--map" in warnings[0], printed.err
    assert "on map dual_lane_4way;" in printed.out and "Traceback" not in printed.err
    assert _same(frames, _render(path, out, "--map", "dual_lane_4way"))
    _render(path, out, "--map", MAP)                          # named explicitly: no warning
    assert "warning" not in capsys.readouterr().err


def test_posed_map_renders_like_the_same_map_at_the_origin(tmp_path, capsys):
    """A map file's pose moves the recorded states (the world publishes in the fixed map frame);
    render-bag draws them in the map's own frame, on its road: the picture is the unposed one."""
    import yaml

    from bimacppo_sim.road import MAP_DIR
    spec = yaml.safe_load((MAP_DIR / f"{MAP}.yaml").read_text())
    spec["pose"] = {"x": 412.0, "y": -318.5, "heading": 0.6}
    posed = tmp_path / "posed.yaml"
    posed.write_text(yaml.safe_dump(spec))
    a, b = tmp_path / "origin.mcap", tmp_path / "posed.mcap"
    _write_bag(a)
    # as our recorder writes it: the map file's path and text
    _write_bag(b, map_id=str(posed), run_metadata={mcap_io.MAP_ID_KEY: str(posed),
                                                   mcap_io.MAP_YAML_KEY: posed.read_text()})
    ga, gb = tmp_path / "origin.gif", tmp_path / "posed.gif"
    assert main(["render-bag", str(a), "-o", str(ga), "--map", MAP, "--every", "10"]) == 0
    assert main(["render-bag", str(b), "-o", str(gb), "--map", str(posed), "--every", "10"]) == 0
    fa, fb = _gif(ga), _gif(gb)
    assert len(fa) == len(fb) >= 5
    for (x, _), (y, _) in zip(fa, fb):
        assert _ev_centre(x) == pytest.approx(_ev_centre(y), abs=1.0)
        assert np.mean(np.any(x != y, axis=2)) < 0.01      # at most sub-pixel edges differ
    # on the unposed map the posed recording lies 500 m away: no EV in view
    gc = tmp_path / "wrong_map.gif"
    assert main(["render-bag", str(b), "-o", str(gc), "--map", MAP, "--every", "10"]) == 0
    with pytest.raises(AssertionError, match="EV not drawn"):
        _ev_centre(_gif(gc)[0][0])
    # without --map: the recorded text, also where the file no longer is
    posed.rename(tmp_path / "moved.yaml")
    capsys.readouterr()
    gd = tmp_path / "recorded_map.gif"
    assert main(["render-bag", str(b), "-o", str(gd), "--every", "10"]) == 0
    printed = capsys.readouterr()
    assert f"on map {posed};" in printed.out and "warning" not in printed.err, printed
    assert _same(_gif(gd), fb)
