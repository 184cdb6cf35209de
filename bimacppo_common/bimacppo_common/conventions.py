"""Conventions every package shares (docs/architecture.md): the task names, the episode
outcomes and how an angle is wrapped. Defined here once; no ROS, no numpy.

* ``TASKS[j]`` names task index j of a scenario Omega_ij (the BiMAB arm's second index);
  ``task_on_map`` says which task an arm runs on a map that offers only some of them.
* ``OUTCOMES`` are the only ways an episode ends, in the order reports list them.
* ``wrap_angle`` maps any angle to (-pi, pi]: heading differences never jump by 2*pi, and
  -pi and pi are the same heading, written pi.

``wrap_angle`` uses only ``math``, so ``bimacppo_mpc._kernels`` compiles this same function
with numba rather than keeping a copy.
"""
from __future__ import annotations

import math

TASKS = ("left", "straight", "right")
OUTCOMES = ("success", "collision", "timeout")

TWO_PI = 2.0 * math.pi


def wrap_angle(a: float) -> float:
    """Wrap to (-pi, pi]. Written with ``math.floor`` only, so numba compiles this function too."""
    r = a + math.pi
    r -= TWO_PI * math.floor(r / TWO_PI)        # [0, 2*pi) up to rounding
    if r <= 0.0:
        r += TWO_PI
    return r - math.pi


def task_on_map(task: str, tasks) -> str:
    """The task a curriculum arm asking for ``task`` runs on a map offering ``tasks``.

    The arm's own task where the map has it. A map with a single task (the straight road of
    the overtaking study) runs that task for every arm, so a curriculum keeps all its arms
    whatever the map: on such a map the task index carries no information, and refusing the
    other arms would only stall the run. Any other missing task is an error."""
    tasks = tuple(tasks)
    if task not in TASKS:
        raise ValueError(f"task must be one of {TASKS}, got {task!r}")
    if task in tasks:
        return task
    if len(tasks) == 1:
        return tasks[0]
    raise ValueError(f"task {task!r} is not available (tasks: {', '.join(tasks) or 'none'})")
