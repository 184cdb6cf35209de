"""Conventions every package shares (docs/architecture.md): the task names, the episode
outcomes and how an angle is wrapped. Defined here once; no ROS, no numpy.

* ``TASKS[j]`` names task index j of a scenario Omega_ij (the BiMAB arm's second index).
* ``OUTCOMES`` are the only ways an episode ends, in the order reports list them.
* ``wrap_angle`` maps any angle to (-pi, pi]: heading differences never jump by 2*pi, and
  -pi and pi are the same heading, written pi.

``bimacppo_mpc._kernels`` keeps a numba-compiled twin of ``wrap_angle`` (same interval): a
compiled kernel cannot call this one.
"""
from __future__ import annotations

import math

TASKS = ("left", "straight", "right")
OUTCOMES = ("success", "collision", "timeout")

TWO_PI = 2.0 * math.pi


def wrap_angle(a: float) -> float:
    """Wrap to (-pi, pi]."""
    a = math.fmod(a + math.pi, TWO_PI)
    if a <= 0.0:
        a += TWO_PI
    return a - math.pi
