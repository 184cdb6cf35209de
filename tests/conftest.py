"""Shared test setup.

ROS graph tests must never see another run's nodes: every pytest session gets
its own DDS domain (derived from the PID, unless ROS_DOMAIN_ID is already set)
and discovery is confined to this machine.
"""
import os
import pathlib

os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("MPLBACKEND", "Agg")

REPO = pathlib.Path(__file__).resolve().parents[1]
