"""A world run's clock that starts after every earlier run's: time never goes back.

Receivers tell episodes apart by the goal's stamp (docs/interfaces.md, "Tick protocol"). That
is an identity only if a new run of the world never re-uses an earlier run's stamps: a world
restarted within its first episode would otherwise send its first goal again with the same
stamp, which no receiver can tell from a repeat, and every tick of the new run would be older
than the ticks the receivers last answered.

So a run reserves its stamps ahead in a small file (a lease) and the next run starts one tick
after the newest reservation. The lease is renewed ``LEASE_S`` of sim time ahead of the clock,
so a run killed at any moment has reserved every stamp it published, and a new run starts at
most ``LEASE_S`` plus a tick after the last stamp the receivers saw: well inside their
``MAX_STAMP_JUMP_S``, so its first goal is simply the newest episode. The file is kept per DDS
domain (runs in other domains never meet the same receivers) under ``$ROS_HOME`` (default
``~/.ros``), where ROS keeps its other per-machine state. A lockstep world runs faster than the
wall clock, so no clock read at launch could promise this; the lease counts sim time.

Pure Python (no rclpy): the world node composes one. A file that cannot be read or written
never stops the world: the run starts at one tick, as a relaunched simulator does, and the
receivers' rule for a source whose time goes back covers it; ``warning`` says why once.
"""
from __future__ import annotations

import fcntl
import math
import os
from pathlib import Path
from typing import Callable, Optional

from .tick_protocol import MAX_STAMP_JUMP_S

LEASE_S = 10.0
"""Sim seconds a run reserves ahead of its clock. Larger means fewer writes (one per
``LEASE_S`` of sim time) but a larger gap between runs, which must stay below the receivers'
``MAX_STAMP_JUMP_S`` so that the next run's first goal is not taken for a far-future stamp."""

assert LEASE_S < MAX_STAMP_JUMP_S / 2

NO_FILE = "none"
"""The ``clock_file`` value for a world without a lease: every run starts at one tick."""


def default_clock_file(env=None) -> Path:
    """``$ROS_HOME/bimacppo/world_clock_domain<ROS_DOMAIN_ID>`` (ROS_HOME defaults to ~/.ros)."""
    env = os.environ if env is None else env
    home = Path(env.get("ROS_HOME") or Path.home() / ".ros")
    return home / "bimacppo" / f"world_clock_domain{env.get('ROS_DOMAIN_ID') or 0}"


class RunClock:
    """Tick counter of one world run: stamp = tick · dt, the first tick after every earlier
    run's lease in ``path`` (``None``: no lease, the first tick is 1).

    Call :meth:`advance` for each new tick; it renews the lease when the clock reaches it."""

    def __init__(self, dt_ns: int, path: Optional[Path], warning: Callable[[str], None] = lambda m: None,
                 lease_s: float = LEASE_S) -> None:
        if dt_ns <= 0:
            raise ValueError(f"RunClock: dt_ns must be > 0, got {dt_ns}")
        if not 0.0 < lease_s < MAX_STAMP_JUMP_S:
            raise ValueError(f"RunClock: lease_s must be in (0, {MAX_STAMP_JUMP_S}), got {lease_s}")
        self.dt_ns = int(dt_ns)
        self.path = None if path is None else Path(path)
        self.warning = warning
        self._bad_text = None                     # the unreadable content already warned about
        self.lease_ticks = max(1, math.ceil(lease_s * 1e9 / self.dt_ns))
        earlier = self._update(lambda old: old)   # newest stamp an earlier run reserved
        self.first_tick = 1 if earlier is None else earlier // self.dt_ns + 1
        self.tick = self.first_tick - 1           # no tick published yet
        self.reserved_tick = self.tick            # the lease is taken with the first tick

    def stamp_ns(self) -> int:
        return self.tick * self.dt_ns

    def advance(self) -> int:
        """The next tick; its stamp (and ``LEASE_S`` beyond) is reserved before it is returned."""
        self.tick += 1
        if self.tick > self.reserved_tick and self.path is not None:
            target = self.tick + self.lease_ticks
            if self._update(lambda old: max(old or 0, target * self.dt_ns)) is not None:
                self.reserved_tick = target
        return self.tick

    # ------------------------------------------------------------------ the file
    def _update(self, new_value: Callable[[Optional[int]], Optional[int]]) -> Optional[int]:
        """Read the reserved stamp under an exclusive lock, write ``new_value(old)`` if it
        differs; the value written (or read), or None when there is no usable file."""
        if self.path is None:
            return None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path.with_name(self.path.name + ".lock"), "a") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)   # two worlds starting at once see one another
                old = self._read()
                new = new_value(old)
                if new is not None and new != old:
                    tmp = self.path.with_name(self.path.name + f".{os.getpid()}.tmp")
                    tmp.write_text(f"{int(new)}\n")
                    os.replace(tmp, self.path)     # a reader sees the old value or the new one
                return new
        except OSError as exc:
            self.warning(f"clock file {self.path}: {exc.strerror or exc}: runs are told apart by "
                         "time going back (no lease)")
            self.path = None
            return None

    def _read(self) -> Optional[int]:
        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return None
        try:
            value = int(text.strip())
            if value < 0:
                raise ValueError("negative")
            return value
        except ValueError:
            if text == self._bad_text:
                return None
            self._bad_text = text
            self.warning(f"clock file {self.path}: not a stamp ({text[:40]!r}): overwritten; this run "
                         "may re-use an earlier run's stamps")
            return None
