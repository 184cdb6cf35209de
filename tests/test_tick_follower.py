"""The goal and stamp rules planner and controller share (``TickFollower``), without DDS.

Each case is an arrival order the fault suite produced on a loaded machine (docs/faults.md):
a bogus latched goal stamped far in the future reaching a restarted node before or after
the world's genuine goal, latched re-deliveries, and a world that really restarted.
"""
import numpy as np
import pytest

pytest.importorskip("rclpy")

from bimacppo_sim.ros import interfaces as I  # noqa: E402
from bimacppo_sim.ros.tick_follower import (GOAL_HISTORY, RESYNC_MIN_S, RESYNC_REPEATS,  # noqa: E402
                                            STALE_RESTART, TickFollower)

S = I.NS_PER_S
TICK = S // 10
GOAL = (-23.0, 1.75, 0.0)
BOGUS_STAMP = 10_013 * S   # the fault suite's far-future goal


class _Log:
    def __init__(self):
        self.lines = []

    def debug(self, msg, **_):
        self.lines.append(("debug", msg))

    def warning(self, msg, **_):
        self.lines.append(("warning", msg))


class Follower(TickFollower):
    """The mixin with the two hooks a node provides."""

    def __init__(self):
        self.log = _Log()
        self.cleared = 0
        self._init_tick_follower(cache_size=16, max_jump_ns=30 * S)
        self.now = 0.0                    # the wall clock of the resync rule, moved by the test
        self._wall = lambda: self.now

    def get_logger(self):
        return self.log

    def _clear_tick_caches(self):
        self.cleared += 1

    def goal(self, stamp, xy=GOAL):
        self._accept_goal(I.goal_to_pose(xy, stamp))

    def state(self, stamp, x=None):
        self._check_order(stamp, "state", _x(stamp) if x is None else x)
        self._note_state(stamp)

    def answer(self, stamp, x=None):
        """What a node does once it answered the tick."""
        x = _x(stamp) if x is None else x
        self.state(stamp, x)
        self.order.answered(stamp)
        self._answered(stamp, f"answer {stamp}", x)


def _x(stamp, run=0):
    """The EV state a source publishes at ``stamp`` (``run``: which start of the source)."""
    return np.array([stamp / S - 20.0 * run, 1.75, 5.0 + run, 0.0])


def test_bogus_goal_after_the_genuine_one_on_a_fresh_node_falls_back():
    f = Follower()
    f.goal(11_900_000_000)
    f.goal(BOGUS_STAMP)                 # nothing to refuse it with yet: no state seen
    assert f.gate.goal_stamp == BOGUS_STAMP
    f.state(23_200_000_000)
    assert f.gate.goal_stamp == 11_900_000_000
    assert f.gate.classify(23_200_000_000) == "active"
    assert f.gate.new_episode()


def test_genuine_goal_after_a_bogus_one_on_a_fresh_node_is_not_a_restart():
    f = Follower()
    f.goal(BOGUS_STAMP)
    f.goal(11_900_000_000)              # older, but no state says time went back
    assert f.cleared == 0 and not any("restarted" in m for _, m in f.log.lines)
    f.state(23_200_000_000)
    assert f.gate.goal_stamp == 11_900_000_000
    assert f.gate.classify(23_300_000_000) == "active"


def test_bogus_goal_alone_is_dropped_and_the_next_resend_of_the_genuine_goal_starts_the_episode():
    f = Follower()
    f.goal(BOGUS_STAMP)
    f.state(23_200_000_000)
    assert f.gate.goal_stamp is None and f.gate.classify(23_200_000_000) == "wait"
    f.goal(11_900_000_000)              # the world's periodic goal re-send
    assert f.gate.goal_stamp == 11_900_000_000
    assert f.gate.classify(23_300_000_000) == "active"


def test_bogus_goal_is_refused_once_states_are_known():
    f = Follower()
    f.goal(100_000_000)
    f.state(100_000_000)
    with pytest.raises(I.MessageError, match="ahead of the newest state"):
        f.goal(BOGUS_STAMP)
    assert f.gate.goal_stamp == 100_000_000


def test_re_deliveries_do_not_push_the_genuine_goal_out_of_the_history():
    f = Follower()
    f.goal(11_900_000_000)
    for _ in range(3 * GOAL_HISTORY):   # latched re-deliveries and periodic re-sends
        f.goal(11_900_000_000)
    f.goal(BOGUS_STAMP)
    assert len(f._goals) == 2
    f.state(12_000_000_000)
    assert f.gate.goal_stamp == 11_900_000_000
    assert [s for s, _ in f._goals] == [11_900_000_000]   # the bogus goal left the history


def test_a_repeat_of_the_current_goal_changes_nothing():
    f = Follower()
    f.goal(11_900_000_000)
    f.state(11_900_000_000)
    assert f.gate.new_episode()
    f.goal(11_900_000_000)
    assert not f.gate.new_episode() and f.cleared == 0
    assert sum(1 for lvl, m in f.log.lines if lvl == "debug" and "episode goal" in m) == 1


def test_an_older_goal_while_states_are_known_is_a_restart():
    f = Follower()
    f.goal(11_900_000_000)
    f.state(12_000_000_000)
    f.goal(100_000_000)                 # the world restarted: its time went back
    assert f.cleared == 1 and f._newest_state is None
    assert f.gate.goal_stamp == 100_000_000
    f.state(100_000_000)                # no longer "stale": the order filter was reset
    assert f.gate.classify(100_000_000) == "active"
    assert any("restarted" in m for lvl, m in f.log.lines if lvl == "warning")


def _ran_first_episode(f, ticks=100):
    f.goal(TICK)
    for k in range(1, ticks + 1):
        f.answer(k * TICK)


def test_a_world_restarted_within_its_first_episode_is_noticed_by_its_stale_states():
    """Same goal stamp again (tick 1), then states from tick 2 on: all older than the newest
    answered tick. The goal rule cannot see it; STALE_RESTART states in a row do."""
    f = Follower()
    _ran_first_episode(f)
    f.goal(TICK, xy=(23.0, -5.25, 0.0))   # the restarted world's first goal: same stamp, new scenario
    for k in range(2, 2 + STALE_RESTART - 1):
        with pytest.raises(I.MessageError, match="stale"):
            f.state(k * TICK)
    assert f.cleared == 0
    f.state((1 + STALE_RESTART) * TICK)   # the run is long enough: a restart, this state accepted
    assert f.cleared == 1 and not f.answers
    assert f.gate.goal_stamp == TICK and tuple(f.gate.goal[:2]) == (23.0, -5.25)   # the goal kept
    assert f.gate.classify((1 + STALE_RESTART) * TICK) == "active" and f.gate.new_episode()
    f.answer((2 + STALE_RESTART) * TICK)   # the new world's ticks are answered from here on


def test_single_late_states_and_resent_ticks_never_restart():
    f = Follower()
    _ran_first_episode(f)
    for k in range(101, 101 + 3 * STALE_RESTART):
        with pytest.raises(I.MessageError, match="stale"):
            f.state(5 * TICK)             # a late sample ...
        f.state(100 * TICK)               # ... and a re-sent tick (already answered) in between
        f.answer(k * TICK)                # ... and the loop going on
    for _ in range(3 * STALE_RESTART):
        f.state(100 * TICK)               # re-sends of an answered tick count as nothing
    assert f.cleared == 0 and f.gate.goal_stamp == TICK


def test_stale_run_restart_drops_goals_after_the_new_time():
    """A world restarted in a later episode whose new goal has not arrived yet: no goal
    of the old world is before its states, so the node waits for the new goal."""
    f = Follower()
    _ran_first_episode(f)
    f.goal(150 * TICK)
    f.answer(150 * TICK)
    for k in range(2, 2 + STALE_RESTART):
        try:
            f.state(k * TICK)
        except I.MessageError:
            pass
    assert f.cleared == 1 and f.gate.goal_stamp is None
    assert f.gate.classify((2 + STALE_RESTART) * TICK) == "wait"
    f.goal(TICK)
    assert f.gate.classify((2 + STALE_RESTART) * TICK) == "active"


def test_a_restarted_world_whose_ticks_are_still_cached_is_not_answered_from_the_cache():
    """The old world ran 10 ticks (all cached), then restarted: its ticks 2.. carry cached
    stamps but other states. They are no re-sends; STALE_RESTART of them restart the node."""
    f = Follower()
    _ran_first_episode(f, ticks=10)
    f.state(5 * TICK)                     # a genuine re-send (same state): answered from the cache
    f.goal(TICK)                          # the restarted world's first goal, same stamp
    for k in range(2, 2 + STALE_RESTART - 1):
        with pytest.raises(I.MessageError, match="differs from the state answered"):
            f.state(k * TICK, _x(k * TICK, run=1))
    assert f.cleared == 0 and 5 * TICK in f.answers
    k = 1 + STALE_RESTART
    f.state(k * TICK, _x(k * TICK, run=1))
    assert f.cleared == 1 and not f.answers
    assert f.gate.goal_stamp == TICK and f.gate.classify(k * TICK) == "active"
    f.answer((k + 1) * TICK, _x((k + 1) * TICK, run=1))


def test_a_result_at_its_goals_stamp_is_refused():
    """An episode lasts at least one step: such a result would end it at its first tick."""
    f = Follower()
    f.goal(TICK)
    f.answer(TICK)
    with pytest.raises(I.MessageError, match="first tick"):
        f._check_result(TICK)
    f._check_result(2 * TICK)             # a genuine result, one step later, passes


# ----------------------------------------------------------------------------- resync
def _resend(f, stamp, times, period_s=0.5):
    """A lockstep source re-sending the tick it waits for; returns the receptions refused."""
    refused = 0
    for _ in range(times):
        f.now += period_s
        try:
            f.state(stamp)
        except I.MessageError:
            refused += 1
        f._classify(stamp)
    return refused


def _resyncs(f):
    return [m for lvl, m in f.log.lines if lvl == "warning" and "following the source" in m]


# (case, how the node comes to refuse the tick the source then re-sends)
def _bogus_result_one_tick_ahead(f):
    f._check_result(51 * TICK)
    f.gate.on_result(51 * TICK)          # a well-formed result stamped at the next tick
    f.state(51 * TICK)
    assert f._classify(51 * TICK) == "stale"
    return 51 * TICK


def _bogus_result_at_the_newest_tick(f):
    f.gate.on_result(50 * TICK)
    f.state(51 * TICK)
    assert f._classify(51 * TICK) == "wait"   # waits for a goal the source will never send
    return 51 * TICK


def _source_far_ahead(f):
    with pytest.raises(I.MessageError, match="jump"):
        f.state(50 * TICK + 40 * S)      # the source's clock went on while the node was elsewhere
    return 50 * TICK + 40 * S


@pytest.mark.parametrize("refuse", [_bogus_result_one_tick_ahead, _bogus_result_at_the_newest_tick,
                                    _source_far_ahead])
def test_a_refused_tick_the_source_keeps_re_sending_resynchronises_the_node(refuse):
    f = Follower()
    _ran_first_episode(f, ticks=50)
    stamp = refuse(f)
    assert _resend(f, stamp, RESYNC_REPEATS - 1) >= 0 and f.cleared == 0 and not _resyncs(f)
    _resend(f, stamp, 1)                 # the RESYNC_REPEATS-th re-send: follow the source
    assert f.cleared == 1 and len(_resyncs(f)) == 1, f.log.lines
    assert f.gate.goal_stamp == TICK and f._classify(stamp) == "active" and f.gate.new_episode()
    assert f.now <= 5.0
    f.answer(stamp)
    _resend(f, stamp, 3 * RESYNC_REPEATS)  # re-sends of the tick now answered: nothing more
    f.answer(stamp + TICK)
    assert f.cleared == 1 and len(_resyncs(f)) == 1


def test_re_sends_faster_than_the_resync_time_wait_for_it():
    f = Follower()
    _ran_first_episode(f, ticks=50)
    stamp = _source_far_ahead(f)
    period = RESYNC_MIN_S / (3 * RESYNC_REPEATS)
    _resend(f, stamp, 3 * RESYNC_REPEATS - 2, period_s=period)
    assert f.cleared == 0                # many re-sends, but within RESYNC_MIN_S
    _resend(f, stamp, 2, period_s=period)
    assert f.cleared == 1


@pytest.mark.parametrize("between", ["answer", "other stamp"])
def test_refusals_while_the_node_answers_or_of_other_stamps_never_resync(between):
    """A late sample refused again and again while newer ticks are answered (the loop moves),
    or refusals of ever new stamps (a realtime source: its far-jump rule is StampFilter's)."""
    f = Follower()
    _ran_first_episode(f, ticks=50)
    # other stamps: fewer than StampFilter's resync_after growing jumps, which it follows itself
    n = 4 * RESYNC_REPEATS if between == "answer" else f.order.resync_after - 1
    for k in range(51, 51 + n):
        f.now += 1.0
        stamp = 5 * TICK if between == "answer" else k * TICK + 40 * S
        with pytest.raises(I.MessageError):
            f.state(stamp)
        if between == "answer":
            f.answer(k * TICK)
    assert f.cleared == 0 and not _resyncs(f)


def test_a_node_without_a_goal_never_resyncs_on_re_sends():
    """No goal yet ("wait" before any episode): nothing to follow; the goal's re-send starts it."""
    f = Follower()
    _resend(f, TICK, 4 * RESYNC_REPEATS, period_s=1.0)
    assert f.cleared == 0 and f._refused is None
    f.goal(TICK)
    assert f._classify(TICK) == "active"
