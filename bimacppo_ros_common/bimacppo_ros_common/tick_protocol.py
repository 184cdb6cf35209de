"""The tick protocol of the nodes that answer a source's ticks (planner, controller).

One pure class, no rclpy: the state/transition table in docs/interfaces.md ("Tick
protocol") is this module. A node composes a :class:`TickProtocol`, hands it every stamped
input and acts on the :class:`Verdict` it returns (answer, send the cached answer again,
keep, drop); the protocol never raises on an input. What it protects against
(docs/faults.md): stale or far-future stamps, a bogus latched goal reaching a fresh node
first, a source that restarts and sends older stamps, results and goals arriving in either
order (DDS orders per topic only), and a node whose view is wrong while the source keeps
re-sending one tick.
"""
from __future__ import annotations

import enum
import time
from collections import OrderedDict, deque
from typing import Callable, Optional

import numpy as np

GOAL_HISTORY = 8
"""Recent goals kept as fallbacks for a goal stamped far ahead of the states."""

STALE_RESTART = 5
"""States in a row older than the newest answered one (none accepted in between) that mean
the source restarted. A late or replayed sample is one message; a restarted source sends
nothing else. This catches the restart the goal rule cannot see: a world restarted within
its first episode re-sends its first goal with the same stamp."""

RESYNC_REPEATS = 3
"""Receptions of a state this node refused (stale, too far ahead, or after its episode's
result), counted after the refusal, that make the node follow the source to that tick.
A lockstep source re-sends the tick it waits for and nothing else, so a refused tick that
keeps coming means the node's view (a result, a newest answered stamp) is wrong and the
source's is right; a single late or injected sample is never re-sent."""

RESYNC_MIN_S = 1.0
"""Wall seconds between the refusal and the resync, at least: a source's re-sends must span
this long (the world re-sends every ``resend_period_s``, 0.5 s by default, so a resync comes
1.5 s after the refusal; a downstream node refuses a tick only once its upstream answers it,
so planner then controller resync within 3 s)."""

MAX_STAMP_JUMP_S = 30.0
"""Default of the nodes' ``max_stamp_jump_s``: how far ahead of the newest answered tick a
stamp may lie and still be taken as the source's next tick. A world run starts within
``run_clock.LEASE_S`` of the previous run's last stamp, so this must stay well above that."""

JUMP_RESYNC_AFTER = 5
"""Stamps in a row more than ``max_jump_ns`` ahead, each newer than the last, that are taken
as a real jump of an open-loop source (it was paused, a peer was gone a while)."""


class Verdict(str, enum.Enum):
    """What a node does with an input (docs/interfaces.md, "Tick protocol")."""
    ANSWER = "answer"     # state/input accepted; classify: compute this tick's answer now
    REPEAT = "repeat"     # a tick already answered with this state: send the cached answer
    RESTART = "restart"   # the node restarted at this state (source restarted or insists); accepted
    WAIT = "wait"         # no goal for this tick yet: keep it until one comes
    STALE = "stale"       # older than the newest answered tick, after its episode, or other values at an answered stamp
    JUMP = "jump"         # more than max_jump ahead of the newest answered tick
    NEW = "new"           # goal: a new episode (or the first goal)
    KEPT = "kept"         # goal older than the current one before any state: kept, the first state picks
    AHEAD = "ahead"       # goal/result more than max_jump ahead of every state
    EARLY = "early"       # result at or before the start of the episode it would end
    ENDS = "ends"         # result of the episode the node holds (its goal's episode was running)
    OVER = "over"         # result while no episode runs (already ended, or none yet)


REFUSED = frozenset({Verdict.STALE, Verdict.JUMP, Verdict.AHEAD, Verdict.EARLY})
"""Verdicts that drop the input (the node logs ``TickProtocol.reason`` and counts it)."""


class EpisodeGate:
    """Which episode a stamped input belongs to, when goal, result and state travel on
    different topics whose relative order DDS does not guarantee.

    An episode starts at its goal's stamp (the world stamps the goal with the first
    state's stamp) and ends at its result's stamp. ``classify(stamp)``: ANSWER, WAIT (no
    goal for it yet) or STALE (older than the current episode, or its terminal state)."""

    def __init__(self) -> None:
        self.goal = None
        self.goal_stamp: Optional[int] = None
        self.result_stamp: int = -1
        self._started: Optional[int] = None

    def on_goal(self, stamp_ns: int, goal) -> bool:
        if self.goal_stamp is not None and stamp_ns < self.goal_stamp:
            return False  # an older goal delivered late
        self.goal, self.goal_stamp = goal, stamp_ns
        return True

    def on_result(self, stamp_ns: int) -> None:
        self.result_stamp = max(self.result_stamp, stamp_ns)

    def classify(self, stamp_ns: int) -> Verdict:
        if self.goal_stamp is None:
            return Verdict.WAIT
        if stamp_ns < self.goal_stamp:
            return Verdict.STALE
        if self.result_stamp >= self.goal_stamp:       # the goal's episode is over
            return Verdict.WAIT if stamp_ns > self.result_stamp else Verdict.STALE
        return Verdict.ANSWER

    def new_episode(self) -> bool:
        """True once per goal: the caller resets its per-episode state."""
        if self._started != self.goal_stamp:
            self._started = self.goal_stamp
            return True
        return False

    def retry_start(self) -> None:
        """The caller could not start the episode: ``new_episode`` is True again."""
        self._started = None

    @property
    def ended(self) -> bool:
        return self.goal_stamp is not None and self.result_stamp >= self.goal_stamp


class StampFilter:
    """Order of the stamps a node answers within one episode.

    Sources publish strictly growing stamps (a lockstep re-send repeats one, and is
    answered from the node's cache before this check). Once a stamp was answered, an older
    stamp is STALE (a late or replayed sample); one more than ``max_jump_ns`` ahead is JUMP
    (a wrong clock or a bogus sender: answering it would make every genuine tick after it
    look stale), unless ``resync_after`` such stamps in a row, each newer than the last,
    show a real jump of the source: the filter follows it."""

    def __init__(self, max_jump_ns: int, resync_after: int = JUMP_RESYNC_AFTER) -> None:
        if max_jump_ns <= 0 or resync_after < 1:
            raise ValueError("StampFilter: max_jump_ns must be > 0 and resync_after >= 1")
        self.max_jump_ns = int(max_jump_ns)
        self.resync_after = int(resync_after)
        self.reset()

    def reset(self) -> None:
        self.newest: Optional[int] = None
        self._jumps: list = []

    def check(self, stamp_ns: int) -> Optional[Verdict]:
        """None (in order) or STALE / JUMP."""
        if self.newest is None:
            return None
        if stamp_ns < self.newest:
            return Verdict.STALE
        if stamp_ns - self.newest > self.max_jump_ns:
            if self._jumps and stamp_ns <= self._jumps[-1]:
                return Verdict.JUMP
            self._jumps.append(stamp_ns)
            if len(self._jumps) >= self.resync_after:
                self.reset()  # follow the source: the next answer sets the new reference point
                return None
            return Verdict.JUMP
        return None

    def answered(self, stamp_ns: int) -> None:
        self.newest = stamp_ns if self.newest is None else max(self.newest, stamp_ns)
        self._jumps = []


def _no_log(level: str, msg: str) -> None:
    pass


class TickProtocol:
    """Episode gate, stamp order, answer cache, goal history, restart and resync rules.

    ``log(level, message)`` ("warning" or "debug") says what the protocol decided;
    ``on_restart()`` is called when the node must drop what it caches per tick (the source
    restarted, or the node follows it to a tick it refused). ``wall`` is the clock of
    ``RESYNC_MIN_S``. After a refusal, ``reason`` says why."""

    def __init__(self, cache_size: int, max_jump_ns: int, log: Callable[[str, str], None] = _no_log,
                 on_restart: Callable[[], None] = lambda: None, wall: Callable[[], float] = time.monotonic):
        self.cache_size = int(cache_size)
        self.order = StampFilter(int(max_jump_ns))
        self.log, self.on_restart, self.wall = log, on_restart, wall
        self.gate = EpisodeGate()
        self.answers: OrderedDict = OrderedDict()   # stamp -> message already sent for that tick
        self._answered_states: OrderedDict = OrderedDict()   # stamp -> the state that answer was for
        self.newest_state: Optional[int] = None     # newest state stamp (bounds goal/result stamps)
        self._goals: deque = deque(maxlen=GOAL_HISTORY)   # recent (stamp, goal)
        self._stale_states = 0                      # stale states in a row (STALE_RESTART)
        self._refused = None                        # [stamp, reason, wall time, receptions since]
        self.restarts = 0
        self.reason = ""

    # ------------------------------------------------------------------ queries
    @property
    def goal(self):
        return self.gate.goal

    @property
    def goal_stamp(self) -> Optional[int]:
        return self.gate.goal_stamp

    @property
    def ended(self) -> bool:
        return self.gate.ended

    @property
    def running(self) -> bool:
        """A goal is held and its episode has not ended."""
        return self.gate.goal_stamp is not None and not self.gate.ended

    def cached(self, stamp: int):
        return self.answers.get(stamp)

    def bound(self, d: OrderedDict) -> None:
        """Keep a node's per-stamp cache at ``cache_size`` entries (oldest out first)."""
        while len(d) > self.cache_size:
            d.popitem(last=False)

    def _refuse(self, verdict: Verdict, reason: str) -> Verdict:
        self.reason = reason
        return verdict

    # ------------------------------------------------------------------ goal and result
    def on_goal(self, stamp: int, goal) -> Verdict:
        """A validated goal. Only a goal *older* than the current one, seen while states are
        known, means the source's time went back (RESTART, then accepted). A goal with the
        current stamp is a re-delivery (REPEAT: changes nothing; a restart on it cleared the
        goal history and let a bogus far-future goal stall the loop). Before any state
        nothing tells a bogus latched goal from a genuine one: an older one is KEPT in the
        history and the first state picks (``_rebase_goal``)."""
        if self._ahead(stamp):
            return self._refuse(Verdict.AHEAD, f"goal stamp {stamp} ns is more than {self.order.max_jump_ns} ns "
                                               f"ahead of the newest state ({self.newest_state} ns)")
        cur = self.gate.goal_stamp
        verdict = Verdict.NEW
        if cur is not None and stamp < cur and self.newest_state is not None:
            self.log("warning", f"goal stamp went back ({stamp} < {cur} ns): source restarted? starting over")
            self._restart()
            verdict = Verdict.RESTART
        elif cur is not None and stamp == cur:
            verdict = Verdict.REPEAT
        elif cur is not None and stamp < cur:
            verdict = Verdict.KEPT
        if verdict in (Verdict.NEW, Verdict.RESTART):
            self.log("debug", f"episode goal ({goal[0]:.2f}, {goal[1]:.2f}) stamped {stamp} ns")
        self.gate.on_goal(stamp, goal)
        self._remember_goal(stamp, goal)
        return verdict

    def on_result(self, stamp: int, start: Optional[int] = None) -> Verdict:
        """A result stamp. AHEAD: far ahead of the states; EARLY: at its episode's first tick
        (an episode lasts at least one step) or not after ``start`` when given (the first
        tick of the episode the node holds: the next goal may already be here, DDS does not
        order result and goal across topics); ENDS: an episode was running (the result ends
        it, or the one before it when the next goal overtook the result); OVER: none was."""
        if self._ahead(stamp):
            return self._refuse(Verdict.AHEAD, f"result stamp {stamp} ns is more than {self.order.max_jump_ns} ns "
                                               f"ahead of the newest state ({self.newest_state} ns)")
        g = self.gate
        if g.goal_stamp is not None and stamp == g.goal_stamp:
            return self._refuse(Verdict.EARLY, f"result stamp {stamp} ns is its episode's first tick "
                                               "(its goal's stamp)")
        if start is not None and stamp <= start:
            return self._refuse(Verdict.EARLY, f"result stamp {stamp} ns is not after the start of the "
                                               f"episode it would end ({start} ns)")
        was_running = self.running
        g.on_result(stamp)
        return Verdict.ENDS if was_running else Verdict.OVER

    def _ahead(self, stamp: int) -> bool:
        return self.newest_state is not None and stamp - self.newest_state > self.order.max_jump_ns

    # ------------------------------------------------------------------ states and inputs
    def on_state(self, stamp: int, state) -> Verdict:
        """A validated state. REPEAT: answered before with this state; ANSWER: in order
        (keep it for ``classify``); RESTART: the node restarted at it (``STALE_RESTART``
        stale states in a row, or a refused tick re-sent ``RESYNC_REPEATS`` times) and it
        is accepted; STALE / JUMP: dropped. A state with an answered stamp but other values
        is no re-send (a restarted source reached a stamp still cached): STALE."""
        r = self._refused
        if self._insisted(stamp):
            self._restart_at(stamp, f"state {stamp} ns refused ({r[1]}) and re-sent {r[3]} times in "
                                    f"{self.wall() - r[2]:.1f} s: following the source")
            self._note_state(stamp)
            return Verdict.RESTART
        if stamp in self.answers:
            if np.array_equal(self._answered_states.get(stamp), state):
                self._note_state(stamp)
                return Verdict.REPEAT
            why, detail = Verdict.STALE, "differs from the state answered at that stamp"
        else:
            why = self.order.check(stamp)
            detail = why.value if why is not None else ""
        self._stale_states = self._stale_states + 1 if why is Verdict.STALE else 0
        if self._stale_states >= STALE_RESTART:
            self._restart_at(stamp, f"{self._stale_states} states in a row older than the newest answered "
                                    f"one ({stamp} < {self.order.newest} ns): source restarted? starting over")
            self._note_state(stamp)
            return Verdict.RESTART
        if why is not None:
            self._note_refusal(stamp, f"{why.value}, newest answered {self.order.newest} ns")
            return self._refuse(why, f"state stamp {stamp} ns {detail} (newest answered {self.order.newest} ns)")
        self._note_state(stamp)
        return Verdict.ANSWER

    def on_input(self, stamp: int, what: str) -> Verdict:
        """Another stamped input of a tick (SVs, a reference): REPEAT (answered), ANSWER, or
        STALE / JUMP by the stamp order alone."""
        if stamp in self.answers:
            return Verdict.REPEAT
        why = self.order.check(stamp)
        if why is not None:
            return self._refuse(why, f"{what} stamp {stamp} ns {why.value} (newest answered {self.order.newest} ns)")
        return Verdict.ANSWER

    def classify(self, stamp: int) -> Verdict:
        """ANSWER (its episode runs), WAIT (no goal for it yet) or STALE, noting the ticks
        refused because their episode is over (STALE, or WAIT after a result)."""
        kind = self.gate.classify(stamp)
        if kind is Verdict.STALE or (kind is Verdict.WAIT and self.gate.ended):
            self._note_refusal(stamp, f"its episode ended at {self.gate.result_stamp} ns" if self.gate.ended
                               else f"older than its goal ({self.gate.goal_stamp} ns)")
        return kind

    def start_episode(self) -> bool:
        """True once per goal, at its first tick answered: the node resets its per-episode
        state (the stamp order starts over with the episode)."""
        if self.gate.new_episode():
            self.order.reset()
            return True
        return False

    def retry_start(self) -> None:
        """The node could not start the episode (e.g. no route yet): try again at the next tick."""
        self.gate.retry_start()

    def current(self, stamp: int) -> bool:
        """Still in order: no newer tick was answered meanwhile."""
        return self.order.check(stamp) is None

    def answered(self, stamp: int, msg, state) -> None:
        """The node answered ``stamp`` with ``msg`` for ``state`` (cached for re-sends; the node
        is not stalled: a refusal before it no longer counts towards ``RESYNC_REPEATS``)."""
        self.order.answered(stamp)
        self._refused = None
        self.answers[stamp] = msg
        self._answered_states[stamp] = np.array(state, dtype=float)
        self.bound(self.answers)
        self.bound(self._answered_states)

    # ------------------------------------------------------------------ internals
    def _note_refusal(self, stamp: int, reason: str) -> None:
        """A tick this node will not answer (``RESYNC_REPEATS``); the first refusal of a stamp
        starts the count, later ones of the same stamp keep it."""
        if self._refused is None or self._refused[0] != stamp:
            self._refused = [stamp, reason, self.wall(), 0]

    def _insisted(self, stamp: int) -> bool:
        """A state with the stamp last refused arrived again: True once the source has re-sent
        it ``RESYNC_REPEATS`` times over at least ``RESYNC_MIN_S``."""
        r = self._refused
        if r is None or r[0] != stamp or stamp in self.answers:
            return False
        r[3] += 1
        return r[3] >= RESYNC_REPEATS and self.wall() - r[2] >= RESYNC_MIN_S

    def _note_state(self, stamp: int) -> None:
        self._rebase_goal(stamp)
        self.newest_state = stamp if self.newest_state is None else max(self.newest_state, stamp)

    def _rebase_goal(self, stamp: int) -> None:
        """A goal stamped far ahead of the states (a bogus latched goal reaching a fresh node
        before any state could expose it) is replaced by the newest goal received that fits
        the states' time, or dropped (then the node waits for the source's next re-send of its
        goal); goals that do not fit leave the history."""
        g = self.gate
        if g.goal_stamp is None or g.goal_stamp - stamp <= self.order.max_jump_ns:
            return
        fits = [(s, goal) for s, goal in self._goals if s - stamp <= self.order.max_jump_ns]
        self._goals.clear()
        self._goals.extend(fits)
        self.log("warning", f"goal stamp {g.goal_stamp} ns is far ahead of the states ({stamp} ns): "
                            f"{'falling back to the goal of ' + str(fits[-1][0]) if fits else 'dropped'}")
        g.goal_stamp, g.goal = fits[-1] if fits else (None, None)
        g.retry_start()

    def _restart(self) -> None:
        """Forget everything of the old run of the source."""
        self.gate = EpisodeGate()
        self.answers.clear()
        self._answered_states.clear()
        self.order.reset()
        self.newest_state = None
        self._goals.clear()
        self._stale_states = 0
        self._refused = None
        self.restarts += 1
        self.on_restart()

    def _restart_at(self, stamp: int, why: str) -> None:
        """Restart at a state the source insists on, keeping the current goal if it is not
        after it (a world restarted within its first episode sent it again with the same
        stamp; a lockstep world re-sends the goal of the episode it runs); an older goal in
        the history belongs to an old run of the source. ``why`` is logged, once."""
        g = self.gate
        keep = (g.goal_stamp, g.goal) if g.goal_stamp is not None and g.goal_stamp <= stamp else None
        self.log("warning", why + (f" (goal of {keep[0]} ns kept)" if keep is not None else " (waiting for a goal)"))
        self._restart()
        if keep is not None:
            self.gate.on_goal(*keep)
            self._remember_goal(*keep)

    def _remember_goal(self, stamp: int, goal) -> None:
        """History of distinct goals, newest last: a re-delivery moves its goal to the end
        instead of adding a copy, so repeats cannot push the genuine goal out."""
        for i, (s, _) in enumerate(self._goals):
            if s == stamp:
                del self._goals[i]
                break
        self._goals.append((stamp, goal))
