"""DDS domain ids for test processes, free of collisions between processes on one machine.

Two pytest sessions in the same DDS domain see each other's nodes (a CI run beside a
developer's run would answer each other's ticks). An id derived from the PID is not enough:
two PIDs can map to the same id. Here a process owns an id while it holds an exclusive
``flock`` on that id's lock file under the system temp dir; the kernel drops the lock when the
process ends, however it ends (``kill -9`` included), so no stale claim survives a crash.

Rules:

* ids are taken from 1..MAX_DOMAIN_ID (Fast DDS accepts 0..232), first from 1..SAFE_DOMAIN_ID:
  on Linux the ports of higher domains may fall into the ephemeral port range. 0 (every ROS
  user's default) and the id in ``ROS_DOMAIN_ID`` at the time of the call (the user's own
  graph, or the caller's own session) are never handed out;
* the scan starts at an offset taken from the PID, so sessions started one after the other do
  not all reuse the same id a finished session has just released;
* an id is held until the process exits; a lock file that cannot be opened (another user's)
  counts as taken; all ids taken is a RuntimeError naming the lock directory.
"""
from __future__ import annotations

import fcntl
import os
import tempfile
from typing import Dict, Iterable, Optional, Sequence

MAX_DOMAIN_ID = 232      # the highest ROS_DOMAIN_ID Fast DDS accepts
SAFE_DOMAIN_ID = 101     # above this, Linux ephemeral ports may collide with the domain's ports
LOCK_PREFIX = "bimacppo-ros-domain-"

_held: Dict[str, int] = {}    # lock path -> fd holding it, for the life of this process (or release)


def lock_path(domain: int, lock_dir: Optional[str] = None) -> str:
    return os.path.join(lock_dir or tempfile.gettempdir(), f"{LOCK_PREFIX}{int(domain)}.lock")


def _rotated(ids: Sequence[int], start: int) -> list:
    ids = list(ids)
    if not ids:
        return []
    k = start % len(ids)
    return ids[k:] + ids[:k]


def _env_domain() -> Optional[int]:
    try:
        return int(os.environ.get("ROS_DOMAIN_ID", ""))
    except ValueError:
        return None


def _try_lock(path: str) -> Optional[int]:
    """An fd holding an exclusive lock on ``path``, or None if another process holds it."""
    try:   # read-only suffices for flock, so another user's lock file can still be tested
        fd = os.open(path, os.O_RDONLY | os.O_CREAT, 0o644)
    except OSError:
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def acquire(avoid: Iterable[int] = (), start: Optional[int] = None, ids: Optional[Sequence[int]] = None,
            lock_dir: Optional[str] = None) -> int:
    """A domain id no other process on this machine holds, locked until this process exits.

    ``avoid``: ids never to return (besides 0 and the current ``ROS_DOMAIN_ID``); ``start``:
    scan offset (default the PID); ``ids``: the candidates (default the rule above);
    ``lock_dir``: where the lock files live (default the system temp dir)."""
    skip = {0, *(int(a) for a in avoid), *held(lock_dir)}
    env = _env_domain()
    if env is not None:
        skip.add(env)
    offset = os.getpid() if start is None else int(start)
    if ids is None:
        order = (_rotated(range(1, SAFE_DOMAIN_ID + 1), offset)
                 + _rotated(range(SAFE_DOMAIN_ID + 1, MAX_DOMAIN_ID + 1), offset))
    else:
        order = _rotated(ids, offset)
    for domain in order:
        if domain in skip or not 0 <= domain <= MAX_DOMAIN_ID:
            continue
        path = lock_path(domain, lock_dir)
        fd = _try_lock(path)
        if fd is not None:
            _held[path] = fd
            return domain
    where = os.path.dirname(lock_path(0, lock_dir))
    raise RuntimeError(f"no free ROS domain id: every candidate is held by another process "
                       f"(lock files {LOCK_PREFIX}<id>.lock in {where})")


def held(lock_dir: Optional[str] = None) -> list:
    """The ids this process holds (in ``lock_dir``, default the system temp dir)."""
    return sorted(d for d in range(MAX_DOMAIN_ID + 1) if lock_path(d, lock_dir) in _held)


def release(domain: int, lock_dir: Optional[str] = None) -> None:
    """Give an id back before the process exits (a no-op for an id not held)."""
    fd = _held.pop(lock_path(domain, lock_dir), None)
    if fd is not None:
        os.close(fd)


def is_held_elsewhere(domain: int, lock_dir: Optional[str] = None) -> bool:
    """Whether another process holds ``domain`` (probes the lock without keeping it)."""
    if lock_path(domain, lock_dir) in _held:
        return False
    fd = _try_lock(lock_path(domain, lock_dir))
    if fd is None:
        return True
    os.close(fd)
    return False
