"""Ride comfort of applied commands: share of ticks at full steering lock, lock-to-lock
reversals between consecutive ticks, and RMS jerk.

A policy can succeed and still drive like no passenger would accept: steering slammed from one
lock to the other in 0.1 s, or braking and accelerating in alternate ticks. These three figures
make that visible in every evaluation table. They are computed from the commands the world
applied, tick by tick, within each episode (the first tick of an episode has no predecessor):

* full lock: |δ| >= δ_max - LOCK_TOLERANCE (δ_max = the vehicle's steering limit);
* lock-to-lock reversal: one tick at one lock, the next at the other;
* jerk: (a_t - a_{t-1}) / dt; RMS over the consecutive pairs;
* go/stop alternation (per decision, from the planner's reference speeds): a decision whose
  reference is a stop (0 m/s) between two that go, or a go between two stops. A planner that
  flips its mind every decision makes the NMPC brake and accelerate in turn.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LOCK_TOLERANCE = 1e-3     # rad: a command this close to the limit counts as at full lock


@dataclass
class Comfort:
    """Running totals over the episodes of one cell (add episodes, read the three figures)."""

    delta_max: float
    dt: float
    ticks: int = 0
    lock_ticks: int = 0
    pairs: int = 0            # consecutive tick pairs within an episode
    reversals: int = 0
    jerk_sq: float = 0.0
    triples: int = 0          # runs of three consecutive decisions within an episode
    alternations: int = 0

    def add_episode(self, commands, ref_speeds=None) -> None:
        """``commands``: (T, 2) array of the [a, δ] applied at each tick of one episode;
        ``ref_speeds``: the reference speed of each of its decisions (optional)."""
        if ref_speeds is not None:
            stop = np.asarray(ref_speeds, dtype=float).reshape(-1) == 0.0
            if len(stop) > 2:
                self.triples += len(stop) - 2
                self.alternations += int(np.count_nonzero((stop[1:-1] != stop[:-2]) & (stop[1:-1] != stop[2:])))
        u = np.asarray(commands, dtype=float).reshape(-1, 2)
        if len(u) == 0:
            return
        at = np.where(u[:, 1] >= self.delta_max - LOCK_TOLERANCE, 1,
                      np.where(u[:, 1] <= -self.delta_max + LOCK_TOLERANCE, -1, 0))
        self.ticks += len(u)
        self.lock_ticks += int(np.count_nonzero(at))
        if len(u) > 1:
            self.pairs += len(u) - 1
            self.reversals += int(np.count_nonzero(at[1:] * at[:-1] == -1))
            self.jerk_sq += float(np.sum((np.diff(u[:, 0]) / self.dt) ** 2))

    @property
    def full_lock_pct(self) -> float:
        return 100.0 * self.lock_ticks / self.ticks if self.ticks else math.nan

    @property
    def reversal_pct(self) -> float:
        """Lock-to-lock reversals per 100 consecutive tick pairs."""
        return 100.0 * self.reversals / self.pairs if self.pairs else math.nan

    @property
    def rms_jerk(self) -> float:
        return math.sqrt(self.jerk_sq / self.pairs) if self.pairs else math.nan

    @property
    def alternation_pct(self) -> float:
        """Go/stop alternations per 100 runs of three consecutive decisions."""
        return 100.0 * self.alternations / self.triples if self.triples else math.nan

    def to_dict(self) -> dict:
        return {"ticks": self.ticks, "lock_ticks": self.lock_ticks, "pairs": self.pairs,
                "reversals": self.reversals, "jerk_sq": self.jerk_sq, "triples": self.triples,
                "alternations": self.alternations}
