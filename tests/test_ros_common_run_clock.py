"""The world's run clock: a run starts after every stamp an earlier run reserved, so time
never goes back across runs, and a run killed at any tick has reserved what it published."""
import multiprocessing as mp
import os

import pytest

from bimacppo_ros_common.run_clock import LEASE_S, NO_FILE, RunClock, default_clock_file
from bimacppo_ros_common.tick_protocol import MAX_STAMP_JUMP_S

DT = 100_000_000   # 0.1 s


def run(path, ticks, **kw):
    clock = RunClock(DT, path, **kw)
    stamps = [clock.stamp_ns() for _ in range(ticks) if clock.advance()]
    return clock, stamps


def test_first_run_starts_at_one_tick_and_later_runs_after_every_earlier_stamp(tmp_path):
    path = tmp_path / "clock"
    _, first = run(path, 250)
    assert first[0] == DT and first == sorted(set(first))
    for ticks in (1, 37, 250):   # killed early, mid-lease, after several renewals
        _, nxt = run(path, ticks)
        assert nxt[0] > first[-1], "a new run re-used an earlier run's stamp"
        # ... and close enough that the receivers take its first goal as the newest episode
        assert nxt[0] - first[-1] <= (LEASE_S + 0.1) * 1e9 + DT
        assert nxt[0] - first[-1] < MAX_STAMP_JUMP_S * 1e9
        first = nxt


def test_lease_is_written_ahead_of_the_clock_not_every_tick(tmp_path):
    path = tmp_path / "clock"
    writes = []
    clock = RunClock(DT, path)
    real = clock._update
    clock._update = lambda f: writes.append(1) or real(f)
    for _ in range(1000):
        clock.advance()
        assert int(path.read_text()) >= clock.stamp_ns()   # every published stamp is reserved
    assert len(writes) <= 1000 // round(LEASE_S * 1e9 / DT) + 1


def test_no_file_means_every_run_starts_at_one_tick(tmp_path):
    for _ in range(2):
        clock, stamps = run(None, 5)
        assert stamps[0] == DT
    assert NO_FILE == "none"


@pytest.mark.parametrize("text", ["", "garbage\n", "-5\n", "1e9\n"])
def test_unreadable_lease_warns_once_starts_at_one_tick_and_is_repaired(tmp_path, text):
    path = tmp_path / "clock"
    path.write_text(text)
    warnings = []
    clock, stamps = run(path, 3, warning=warnings.append)
    assert stamps[0] == DT and len(warnings) == 1 and str(path) in warnings[0]
    assert int(path.read_text()) >= stamps[-1]   # repaired: the next run follows this one
    _, nxt = run(path, 1)
    assert nxt[0] > stamps[-1]


def test_unwritable_folder_warns_and_the_world_still_runs(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")   # a file where the folder should be
    warnings = []
    clock, stamps = run(blocker / "sub" / "clock", 500, warning=warnings.append)
    assert stamps == [DT * (k + 1) for k in range(500)]
    assert len(warnings) == 1 and "no lease" in warnings[0]


def _start(path, q):
    clock = RunClock(DT, path)
    clock.advance()
    q.put(clock.stamp_ns())


def test_runs_starting_together_each_take_their_own_lease(tmp_path):
    """Two processes starting at once: the lock makes one read the other's lease or neither's,
    never a half-written file."""
    path = tmp_path / "clock"
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    ps = [ctx.Process(target=_start, args=(path, q)) for _ in range(4)]
    for p in ps:
        p.start()
    for p in ps:
        p.join(20)
    got = [q.get(timeout=5) for _ in ps]
    assert all(s > 0 for s in got)
    assert int(path.read_text()) >= max(got)


def test_default_file_is_per_domain_under_ros_home(tmp_path):
    a = default_clock_file({"ROS_HOME": str(tmp_path), "ROS_DOMAIN_ID": "7"})
    b = default_clock_file({"ROS_HOME": str(tmp_path), "ROS_DOMAIN_ID": "8"})
    assert a.parent == tmp_path / "bimacppo" and a != b
    assert default_clock_file({}).parent == default_clock_file({"HOME": os.environ.get("HOME", "")}).parent


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError):
        RunClock(0, None)
    with pytest.raises(ValueError):
        RunClock(DT, None, lease_s=MAX_STAMP_JUMP_S)
