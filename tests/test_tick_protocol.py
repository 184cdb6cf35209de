"""The tick protocol planner and controller share (``TickProtocol``), without DDS: table-driven.

Each case is a sequence of inputs with the verdict each must get (docs/interfaces.md, "Tick
protocol"), then checks of the protocol's state. Most are arrival orders the fault suite
produced on a loaded machine (docs/faults.md): a bogus latched goal stamped far in the future
reaching a fresh node before or after the genuine one, latched re-deliveries, a world that
really restarted, a source whose ticks the node keeps refusing.
"""
import numpy as np
import pytest

from bimacppo_ros_common.run_clock import LEASE_S
from bimacppo_ros_common.tick_protocol import (GOAL_HISTORY, REFUSED, RESYNC_MIN_S, RESYNC_REPEATS,
                                            STALE_RESTART, TickProtocol, Verdict)

V = Verdict
S = 1_000_000_000
TICK = S // 10
GOAL = (-23.0, 1.75, 0.0)
OTHER_GOAL = (23.0, -5.25, 0.0)
BOGUS = 10_013 * S              # the fault suite's far-future goal
G = 11_900_000_000              # a genuine goal's stamp
NEXT_RUN = 50 * TICK + int(LEASE_S * S) + TICK   # the latest a new run starts after 50 ticks of the last


def _x(stamp, run=0):
    """The EV state a source publishes at ``stamp`` (``run``: which start of the source)."""
    return np.array([stamp / S - 20.0 * run, 1.75, 5.0 + run, 0.0])


class Node:
    """What a node does with the protocol: the inputs, its answers, a wall clock moved by the test."""

    def __init__(self):
        self.now = 0.0
        self.cleared = 0
        self.logs = []
        self.p = TickProtocol(16, 30 * S, log=lambda lvl, m: self.logs.append((lvl, m)),
                              on_restart=self._cleared, wall=lambda: self.now)

    def _cleared(self):
        self.cleared += 1

    def warnings(self, text):
        return [m for lvl, m in self.logs if lvl == "warning" and text in m]

    def do(self, op, stamp=None, arg=None):
        p = self.p
        if op == "goal":
            return p.on_goal(stamp, np.array(arg or GOAL))
        if op == "state":
            return p.on_state(stamp, _x(stamp) if arg is None else arg)
        if op == "answer":        # a state that the node then answers
            x = _x(stamp) if arg is None else arg
            v = p.on_state(stamp, x)
            if v not in REFUSED and p.classify(stamp) is V.ANSWER:
                p.start_episode()
                p.answered(stamp, f"answer {stamp}", x)
            return v
        if op == "result":
            return p.on_result(stamp, arg)
        if op == "classify":
            return p.classify(stamp)
        if op == "input":
            return p.on_input(stamp, "objects")
        if op == "wait":
            self.now += stamp
            return None
        raise AssertionError(op)


def episode(ticks=100, goal=TICK):
    """A first episode: its goal, then ``ticks`` states answered."""
    return [("goal", goal, None, V.NEW)] + [("answer", k * TICK, None, V.ANSWER) for k in range(1, ticks + 1)]


def resend(stamp, times, period=0.5, expect=None):
    """A lockstep source re-sending the tick it waits for (the node classifies each)."""
    out = []
    for _ in range(times):
        out += [("wait", period, None, None), ("state", stamp, None, expect), ("classify", stamp, None, None)]
    return out


CASES = [
    ("bogus goal after the genuine one on a fresh node falls back",
     [("goal", G, None, V.NEW), ("goal", BOGUS, None, V.NEW), ("state", 23_200_000_000, None, V.ANSWER),
      ("classify", 23_200_000_000, None, V.ANSWER)],
     lambda n: n.p.goal_stamp == G and n.warnings("falling back to the goal of") and n.p.start_episode()),
    ("genuine goal after a bogus one on a fresh node is no restart",
     [("goal", BOGUS, None, V.NEW), ("goal", G, None, V.KEPT), ("state", 23_200_000_000, None, V.ANSWER),
      ("classify", 23_300_000_000, None, V.ANSWER)],
     lambda n: n.cleared == 0 and not n.warnings("restarted") and n.p.goal_stamp == G),
    ("bogus goal alone is dropped; the next re-send of the genuine goal starts the episode",
     [("goal", BOGUS, None, V.NEW), ("state", 23_200_000_000, None, V.ANSWER),
      ("classify", 23_200_000_000, None, V.WAIT), ("goal", G, None, V.NEW),
      ("classify", 23_300_000_000, None, V.ANSWER)],
     lambda n: n.p.goal_stamp == G and n.warnings("dropped")),
    ("bogus goal refused once states are known",
     [("goal", TICK, None, V.NEW), ("state", TICK, None, V.ANSWER), ("goal", BOGUS, None, V.AHEAD)],
     lambda n: n.p.goal_stamp == TICK and "ahead of the newest state" in n.p.reason),
    ("re-deliveries do not push the genuine goal out of the history",
     [("goal", G, None, V.NEW)] + [("goal", G, None, V.REPEAT)] * (3 * GOAL_HISTORY)
     + [("goal", BOGUS, None, V.NEW), ("state", 12_000_000_000, None, V.ANSWER)],
     lambda n: n.p.goal_stamp == G and [s for s, _ in n.p._goals] == [G]),
    ("a repeat of the current goal changes nothing",
     [("goal", G, None, V.NEW), ("answer", G, None, V.ANSWER), ("goal", G, None, V.REPEAT)],
     lambda n: not n.p.start_episode() and n.cleared == 0
     and sum(1 for lvl, m in n.logs if lvl == "debug" and "episode goal" in m) == 1),
    ("an older goal while states are known is a restart",
     [("goal", G, None, V.NEW), ("state", 12_000_000_000, None, V.ANSWER), ("goal", TICK, None, V.RESTART),
      ("state", TICK, None, V.ANSWER), ("classify", TICK, None, V.ANSWER)],
     lambda n: n.cleared == 1 and n.p.goal_stamp == TICK and n.warnings("restarted")),
    ("a world restarted within its first episode is noticed by its stale states",
     episode() + [("goal", TICK, OTHER_GOAL, V.REPEAT)]
     + [("state", k * TICK, None, V.STALE) for k in range(2, 1 + STALE_RESTART)]
     + [("state", (1 + STALE_RESTART) * TICK, None, V.RESTART),
        ("classify", (1 + STALE_RESTART) * TICK, None, V.ANSWER), ("answer", (2 + STALE_RESTART) * TICK, None, V.ANSWER)],
     lambda n: n.cleared == 1 and n.p.goal_stamp == TICK and tuple(n.p.goal[:2]) == OTHER_GOAL[:2]),
    ("a world restarted mid-episode on its run clock: its goal is simply the newest episode",
     episode(50) + [("goal", NEXT_RUN, OTHER_GOAL, V.NEW), ("answer", NEXT_RUN, _x(NEXT_RUN, run=1), V.ANSWER),
                    ("answer", NEXT_RUN + TICK, _x(NEXT_RUN + TICK, run=1), V.ANSWER)],
     lambda n: n.cleared == 0 and not [m for lvl, m in n.logs if lvl == "warning"]
     and n.p.goal_stamp == NEXT_RUN and tuple(n.p.goal[:2]) == OTHER_GOAL[:2]),
    ("single late states and re-sent ticks never restart",
     episode() + sum(([("state", 5 * TICK, None, V.STALE), ("state", 100 * TICK, None, V.REPEAT),
                       ("answer", k * TICK, None, V.ANSWER)] for k in range(101, 101 + 3 * STALE_RESTART)), [])
     + [("state", 100 * TICK, None, V.REPEAT)] * (3 * STALE_RESTART),
     lambda n: n.cleared == 0 and n.p.goal_stamp == TICK),
    ("a stale-run restart drops goals after the new time",
     episode() + [("goal", 150 * TICK, None, V.NEW), ("answer", 150 * TICK, None, V.ANSWER)]
     + [("state", k * TICK, None, V.STALE) for k in range(2, 1 + STALE_RESTART)]
     + [("state", (1 + STALE_RESTART) * TICK, None, V.RESTART),
        ("classify", (2 + STALE_RESTART) * TICK, None, V.WAIT), ("goal", TICK, None, V.NEW),
        ("classify", (2 + STALE_RESTART) * TICK, None, V.ANSWER)],
     lambda n: n.cleared == 1 and n.warnings("waiting for a goal")),
    ("a restarted world whose ticks are still cached is not answered from the cache",
     episode(10) + [("state", 5 * TICK, None, V.REPEAT), ("goal", TICK, None, V.REPEAT)]
     + [("state", k * TICK, _x(k * TICK, run=1), V.STALE) for k in range(2, 1 + STALE_RESTART)]
     + [("state", (1 + STALE_RESTART) * TICK, _x((1 + STALE_RESTART) * TICK, run=1), V.RESTART),
        ("classify", (1 + STALE_RESTART) * TICK, None, V.ANSWER)],
     lambda n: n.cleared == 1 and not n.p.answers and n.p.goal_stamp == TICK),
    ("a result at its goal's stamp is refused, one step later it ends the episode",
     [("goal", TICK, None, V.NEW), ("answer", TICK, None, V.ANSWER), ("result", TICK, None, V.EARLY),
      ("result", 2 * TICK, None, V.ENDS), ("result", 3 * TICK, None, V.OVER)],
     lambda n: n.p.ended),
    ("a result not after the first tick the node holds is refused; one overtaken by the next goal counts",
     episode(5) + [("goal", 6 * TICK, None, V.NEW), ("result", TICK, TICK, V.EARLY),
                   ("result", 5 * TICK, TICK, V.ENDS)],
     lambda n: not n.p.ended and n.p.goal_stamp == 6 * TICK),
    ("a result far ahead of every state is refused",
     episode(3) + [("result", 3 * TICK + 40 * S, None, V.AHEAD)],
     lambda n: not n.p.ended and "ahead of the newest state" in n.p.reason),
    ("objects and references: repeat, in order, stale, far jump",
     episode(5) + [("input", 5 * TICK, None, V.REPEAT), ("input", 6 * TICK, None, V.ANSWER),
                   ("input", 2 * TICK + TICK // 2, None, V.STALE), ("input", 6 * TICK + 40 * S, None, V.JUMP)],
     lambda n: "jump" in n.p.reason),
    # ------------------------------------------------------------------ resync
    ("bogus result one tick ahead: the re-sent tick resynchronises",
     episode(50) + [("result", 51 * TICK, None, V.ENDS), ("state", 51 * TICK, None, V.ANSWER),
                    ("classify", 51 * TICK, None, V.STALE)]
     + resend(51 * TICK, RESYNC_REPEATS - 1, expect=V.ANSWER) + resend(51 * TICK, 1, expect=V.RESTART)
     + [("classify", 51 * TICK, None, V.ANSWER), ("answer", 52 * TICK, None, V.ANSWER)]
     + resend(52 * TICK, 3 * RESYNC_REPEATS, expect=V.REPEAT),
     lambda n: n.cleared == 1 and len(n.warnings("following the source")) == 1 and n.p.goal_stamp == TICK),
    ("bogus result at the newest tick: the re-sent next tick waits, then resynchronises",
     episode(50) + [("result", 50 * TICK, None, V.ENDS), ("state", 51 * TICK, None, V.ANSWER),
                    ("classify", 51 * TICK, None, V.WAIT)]
     + resend(51 * TICK, RESYNC_REPEATS - 1, expect=V.ANSWER) + resend(51 * TICK, 1, expect=V.RESTART)
     + [("classify", 51 * TICK, None, V.ANSWER)],
     lambda n: n.cleared == 1 and len(n.warnings("its episode ended at")) == 1),
    ("the source's clock far ahead: its re-sent tick resynchronises",
     episode(50) + [("state", 50 * TICK + 40 * S, None, V.JUMP)]
     + resend(50 * TICK + 40 * S, RESYNC_REPEATS - 1, expect=V.JUMP)
     + resend(50 * TICK + 40 * S, 1, expect=V.RESTART) + [("classify", 50 * TICK + 40 * S, None, V.ANSWER)],
     lambda n: n.cleared == 1 and len(n.warnings("jump, newest answered")) == 1),
    ("re-sends faster than RESYNC_MIN_S wait for it",
     episode(50) + [("state", 50 * TICK + 40 * S, None, V.JUMP)]
     + resend(50 * TICK + 40 * S, 3 * RESYNC_REPEATS - 2, period=RESYNC_MIN_S / (3 * RESYNC_REPEATS), expect=V.JUMP)
     + resend(50 * TICK + 40 * S, 2, period=RESYNC_MIN_S / (3 * RESYNC_REPEATS)),
     lambda n: n.cleared == 1),
    ("a late sample refused again and again while the loop answers never resyncs",
     episode(50) + sum(([("wait", 1.0, None, None), ("state", 5 * TICK, None, V.STALE),
                         ("answer", k * TICK, None, V.ANSWER)] for k in range(51, 51 + 4 * RESYNC_REPEATS)), []),
     lambda n: n.cleared == 0 and not n.warnings("following the source")),
    ("refusals of ever new far stamps are the jump rule's, not the resync's",
     episode(50) + [x for k in range(51, 51 + 4)
                    for x in (("wait", 1.0, None, None), ("state", k * TICK + 40 * S, None, V.JUMP))],
     lambda n: n.cleared == 0),
    ("no goal yet: re-sends never resync; the goal's re-send starts the episode",
     resend(TICK, 4 * RESYNC_REPEATS, period=1.0, expect=V.ANSWER)
     + [("classify", TICK, None, V.WAIT), ("goal", TICK, None, V.NEW), ("classify", TICK, None, V.ANSWER)],
     lambda n: n.cleared == 0 and n.p._refused is None),
]


@pytest.mark.parametrize("name, steps, check", CASES, ids=[c[0] for c in CASES])
def test_tick_protocol(name, steps, check):
    n = Node()
    for i, (op, stamp, arg, expect) in enumerate(steps):
        got = n.do(op, stamp, arg)
        if expect is not None:
            assert got is expect, (i, op, stamp, got, n.p.reason, n.logs[-3:])
    assert check(n), (n.logs[-5:], n.p.reason)


def test_resync_comes_within_the_documented_time_at_the_worlds_re_send_period():
    """World re-sends every 0.5 s: the planner follows after RESYNC_REPEATS re-sends, the
    controller (refusing only once the planner answers) as many later: within 5 s."""
    n = Node()
    for op, stamp, arg, _ in episode(50) + [("result", 51 * TICK, None, None)]:
        n.do(op, stamp, arg)
    n.do("state", 51 * TICK)
    n.do("classify", 51 * TICK)
    while n.cleared == 0:
        n.do("wait", 0.5)
        n.do("state", 51 * TICK)
    assert n.now <= 2.5 and 2 * n.now <= 5.0


def test_refused_verdicts_are_exactly_the_dropping_ones():
    assert REFUSED == {V.STALE, V.JUMP, V.AHEAD, V.EARLY}
    assert all(isinstance(v.value, str) for v in V)
