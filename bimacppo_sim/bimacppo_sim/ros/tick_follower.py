"""The stamp and episode bookkeeping shared by the nodes that answer the world's ticks.

Planner and controller both answer stamped states, one message per tick, and both must
survive the same faults (docs/faults.md): stale or far-future stamps, a bogus latched
goal reaching a fresh node first, a source that restarts and sends older stamps, results
and goals arriving in either order (DDS orders per topic only). Keeping those rules in
one place keeps the two nodes from drifting apart; each node adds only what it caches
per tick (``_clear_tick_caches``).

No rclpy import: the mixin uses only ``self.get_logger()`` of the rclpy ``Node`` it is
mixed into, so it is importable (and testable) without a ROS context.
"""
from __future__ import annotations

import time
from collections import OrderedDict, deque

import numpy as np

from . import interfaces as I

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


class TickFollower:
    """Mixin: episode gate, stamp order filter, answer cache and goal handling."""

    def _init_tick_follower(self, cache_size: int, max_jump_ns: int) -> None:
        self.cache_size = int(cache_size)
        self.order = I.StampFilter(int(max_jump_ns))
        self.gate = I.EpisodeGate()
        self.answers: OrderedDict = OrderedDict()   # stamp -> message already sent for that tick
        self._answered_states: OrderedDict = OrderedDict()   # stamp -> the state that answer was for
        self._newest_state = None                   # newest state stamp (bounds goal/result stamps)
        self._goals: deque = deque(maxlen=GOAL_HISTORY)   # recent (stamp, goal)
        self._stale_states = 0                      # stale states in a row (STALE_RESTART)
        self._refused = None                        # [stamp, reason, wall time, receptions since]
        self._wall = time.monotonic                 # the clock of RESYNC_MIN_S

    def _clear_tick_caches(self) -> None:
        """Drop what the node caches per tick (states, pending inputs); called on a restart."""

    def _bounded(self, d: OrderedDict) -> None:
        while len(d) > self.cache_size:
            d.popitem(last=False)

    def _check_ahead(self, stamp: int, what: str) -> None:
        """A goal/result far ahead of every state seen would park the episode: refuse it."""
        if self._newest_state is not None and stamp - self._newest_state > self.order.max_jump_ns:
            raise I.MessageError(f"{what} stamp {stamp} ns is more than {self.order.max_jump_ns} ns "
                                 f"ahead of the newest state ({self._newest_state} ns)")

    def _answered(self, stamp: int, msg, state) -> None:
        """Cache the answer sent for a tick, with the state it answered (the node is not
        stalled: a refusal before it no longer counts towards ``RESYNC_REPEATS``)."""
        self._refused = None
        self.answers[stamp] = msg
        self._answered_states[stamp] = np.array(state, dtype=float)
        self._bounded(self.answers)
        self._bounded(self._answered_states)

    def _check_result(self, stamp: int) -> None:
        """Refuse a result that cannot end the current episode genuinely: stamped far ahead
        of the states, or at the episode's first tick (an episode lasts at least one step;
        the fault suite's stale result at tick 1 ended the first episode and stalled it)."""
        self._check_ahead(stamp, "result")
        if self.gate.goal_stamp is not None and stamp == self.gate.goal_stamp:
            raise I.MessageError(f"result stamp {stamp} ns is its episode's first tick (its goal's stamp)")

    def _refuse(self, stamp: int, reason: str) -> None:
        """Note a tick this node will not answer (``RESYNC_REPEATS``); the first refusal of a
        stamp starts the count, later ones of the same stamp keep it."""
        if self._refused is None or self._refused[0] != stamp:
            self._refused = [stamp, reason, self._wall(), 0]

    def _insisted(self, stamp: int) -> bool:
        """A state with the stamp last refused arrived again: True once the source has re-sent
        it ``RESYNC_REPEATS`` times over at least ``RESYNC_MIN_S``."""
        r = self._refused
        if r is None or r[0] != stamp or stamp in self.answers:
            return False
        r[3] += 1
        return r[3] >= RESYNC_REPEATS and self._wall() - r[2] >= RESYNC_MIN_S

    def _classify(self, stamp: int) -> str:
        """``EpisodeGate.classify``, noting the ticks refused because their episode is over
        (``"stale"``, or ``"wait"`` after a result: no goal of a new episode yet)."""
        kind = self.gate.classify(stamp)
        if kind == "stale" or (kind == "wait" and self.gate.ended):
            self._refuse(stamp, f"its episode ended at {self.gate.result_stamp} ns" if self.gate.ended
                         else f"older than its goal ({self.gate.goal_stamp} ns)")
        return kind

    def _check_order(self, stamp: int, what: str, state=None) -> None:
        """Refuse a stale or far-future stamp; a re-sent tick (already answered, the same
        ``state``) passes. A state with an answered stamp but other values is no re-send:
        a restarted source reached a stamp still cached (it counts as stale).
        ``STALE_RESTART`` stale states in a row restart the node at this state's time; a
        refused state re-sent ``RESYNC_REPEATS`` times resynchronises the node to it."""
        if what == "state" and self._insisted(stamp):
            r = self._refused
            self._restart_at(stamp, f"state {stamp} ns refused ({r[1]}) and re-sent {r[3]} times in "
                                    f"{self._wall() - r[2]:.1f} s: following the source")
            return
        if stamp in self.answers:
            if state is None or np.array_equal(self._answered_states.get(stamp), state):
                return
            why = "stale"
            detail = "differs from the state answered at that stamp"
        else:
            why = detail = self.order.check(stamp)
        if what == "state":
            self._stale_states = self._stale_states + 1 if why == "stale" else 0
            if self._stale_states >= STALE_RESTART:
                self._restart_at(stamp, f"{self._stale_states} states in a row older than the newest "
                                        f"answered one ({stamp} < {self.order.newest} ns): source "
                                        "restarted? starting over")
                return
            if why is not None:
                self._refuse(stamp, f"{why}, newest answered {self.order.newest} ns")
        if why is not None:
            raise I.MessageError(f"{what} stamp {stamp} ns {detail} (newest answered {self.order.newest} ns)")

    def _rebase_goal(self, stamp: int) -> None:
        """A goal stamped far ahead of the states (a bogus latched goal reaching a fresh
        node before any state could expose it) is replaced by the newest goal received
        that fits the states' time, or dropped (then the node waits for the world's next
        re-send of its goal); goals that do not fit leave the history."""
        g = self.gate
        if g.goal_stamp is None or g.goal_stamp - stamp <= self.order.max_jump_ns:
            return
        fits = [(s, goal) for s, goal in self._goals if s - stamp <= self.order.max_jump_ns]
        self._goals.clear()
        self._goals.extend(fits)
        self.get_logger().warning(f"goal stamp {g.goal_stamp} ns is far ahead of the states ({stamp} ns): "
                                  f"{'falling back to the goal of ' + str(fits[-1][0]) if fits else 'dropped'}",
                                  throttle_duration_sec=1.0)
        g.goal_stamp, g.goal = fits[-1] if fits else (None, None)
        g._started = None

    def _note_state(self, stamp: int) -> None:
        """Bookkeeping for a state that passed ``_check_order``."""
        self._rebase_goal(stamp)
        self._newest_state = stamp if self._newest_state is None else max(self._newest_state, stamp)

    def _restart(self) -> None:
        """The source's time went back (world restarted): forget the old episode."""
        self.gate = I.EpisodeGate()
        self.answers.clear()
        self._answered_states.clear()
        self.order.reset()
        self._newest_state = None
        self._goals.clear()
        self._stale_states = 0
        self._refused = None
        self._clear_tick_caches()

    def _restart_at(self, stamp: int, why: str) -> None:
        """Restart at a state the source insists on (a run of stale states, a refused tick
        re-sent), keeping the current goal if it is not after it (a world restarted within
        its first episode sent it again with the same stamp; a lockstep world re-sends the
        goal of the episode it runs); an older goal in the history belongs to an old run of
        the source. ``why`` is logged, once per restart."""
        g = self.gate
        keep = (g.goal_stamp, g.goal) if g.goal_stamp is not None and g.goal_stamp <= stamp else None
        kept = f" (goal of {keep[0]} ns kept)" if keep is not None else " (waiting for a goal)"
        self.get_logger().warning(why + kept)
        self._restart()
        if keep is not None:
            self.gate.on_goal(*keep)
            self._remember_goal(*keep)

    def _remember_goal(self, stamp: int, goal) -> None:
        """History of distinct goals, newest last: a re-delivery (latched topic, the world's
        periodic re-send) moves its goal to the end instead of adding a copy, so repeats
        cannot push the genuine goal out of the history a rebase falls back on."""
        for i, (s, _) in enumerate(self._goals):
            if s == stamp:
                del self._goals[i]
                break
        self._goals.append((stamp, goal))

    def _accept_goal(self, msg) -> None:
        """Validate a /goal_pose message and start its episode (restarting on a stamp that went back)."""
        goal = I.pose_to_goal(msg)
        stamp = I.stamp_to_ns(msg.header.stamp)
        self._check_ahead(stamp, "goal")
        # Only a goal *older* than the current one, seen while states are known, means the
        # source's time went back. A goal with the current goal's stamp is a re-delivery and
        # must not reset anything: treating it as a restart cleared the goal history and let
        # a bogus far-future goal stall the loop (fault suite). Before any state, nothing
        # can tell a bogus latched goal from a genuine one; both are kept and the first
        # state picks (``_rebase_goal``). A world restarted within its first episode
        # re-sends that same stamp: its stale states restart the node (``STALE_RESTART``).
        cur = self.gate.goal_stamp
        if cur is not None and stamp < cur and self._newest_state is not None:
            self.get_logger().warning(f"goal stamp went back ({stamp} < {cur} ns): "
                                      "source restarted? starting over")
            self._restart()
            cur = None
        if cur is None or stamp > cur:
            self.get_logger().debug(f"episode goal ({goal[0]:.2f}, {goal[1]:.2f}) stamped {stamp} ns")
        self.gate.on_goal(stamp, goal)
        self._remember_goal(stamp, goal)
