"""Shared test setup.

ROS graph tests must never see another run's nodes: every pytest session holds a DDS domain of
its own for its whole life (``ros_domain.acquire``: a lock per id, so concurrent sessions on one
machine never share one; never 0 nor the ROS_DOMAIN_ID the session was started with, which is
the user's own graph), exported as ROS_DOMAIN_ID to everything the tests start, and discovery
is confined to this machine. A test that needs a further domain of its own takes it from
``ros_domain.acquire`` too. ROS_HOME is a folder of the session's own.
"""
import atexit
import os
import pathlib
import shutil
import tempfile

import ros_domain

if not ros_domain.held():   # once per process, also if this module is imported again by name
    os.environ["ROS_DOMAIN_ID"] = str(ros_domain.acquire())
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
if not os.environ.get("BIMACPPO_TEST_ROS_HOME"):
    # per-machine ROS state (logs, the world's run-clock lease) in a folder of this session's
    # own: a session's first world starts at one tick whatever ran before on the machine
    os.environ["BIMACPPO_TEST_ROS_HOME"] = os.environ["ROS_HOME"] = tempfile.mkdtemp(prefix="bimacppo-ros-home-")
    atexit.register(shutil.rmtree, os.environ["ROS_HOME"], True)
os.environ.setdefault("MPLBACKEND", "Agg")

REPO = pathlib.Path(__file__).resolve().parents[1]


def load_script(name: str):
    """``scripts/<name>.py`` as a module (the scripts are files, not an installed package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def pytest_report_header(config):
    return f"ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']} (held by this session), discovery LOCALHOST"
