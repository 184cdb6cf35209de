"""bimacppo_common: what the bimacppo packages share. It imports none of them and no ROS, so
every package may depend on it without a cycle (the configuration mechanism: ``config``).

Importing it makes idle OpenMP threads sleep (``OMP_WAIT_POLICY=PASSIVE``) unless the user set a
policy. A training process has one OpenMP runtime, torch's, which numba's parallel NMPC batch
shares; by default its idle threads spin for a while after each parallel call, and runs sharing
the cores then spin against each other's work (docs/results.md, "Two runs on the same cores").
The runtime reads the variable once, when it loads at ``import torch`` (or at numba's first
parallel call when torch is absent). So every package that can load it imports this package
first (bimacppo_mpc, bimacppo_planner, bimacppo_learning); a program that imports torch before
any of them keeps OpenMP's default. A policy set in the environment is kept: a run that has the
machine to itself gains from a bounded spin (docs/ppo.md, "Idle OpenMP threads").
"""
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
