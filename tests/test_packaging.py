"""The colcon workspace builds with the pip-installed ROS and installs what `ros2 run` looks for."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO

EXECUTABLES = {
    "bimacppo_sim": ["world_node", "mcap_recorder", "mcap_player", "bimacppo-sim"],
    "bimacppo_mpc": ["controller_node"],
    "bimacppo_curriculum": ["curriculum_node"],
    "bimacppo_planner": ["planner_node", "bimacppo-graph", "bimacppo-train", "bimacppo-evaluate"],
}


@pytest.fixture(scope="module")
def colcon_install(tmp_path_factory):
    colcon = Path(sys.executable).with_name("colcon")
    if not colcon.exists():
        pytest.fail("colcon is not installed in the test environment (scripts/install.sh installs it)")
    base = tmp_path_factory.mktemp("colcon")
    env = dict(os.environ, AMENT_PREFIX_PATH=str(Path(sys.executable).parents[1]))
    proc = subprocess.run(
        [str(colcon), "--log-base", str(base / "log"), "build", "--base-paths", str(REPO / "ros2_ws" / "src"),
         "--build-base", str(base / "build"), "--install-base", str(base / "install")],
        cwd=base, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    yield base / "install"
    shutil.rmtree(base, ignore_errors=True)


def test_colcon_build_installs_every_package_and_executable(colcon_install):
    for pkg, exes in EXECUTABLES.items():
        share = colcon_install / pkg / "share"
        assert (share / pkg / "package.xml").is_file()
        assert (share / "ament_index" / "resource_index" / "packages" / pkg).is_file()
        for exe in exes:
            path = colcon_install / pkg / "lib" / pkg / exe
            assert path.is_file() and os.access(path, os.X_OK), f"{path} missing: ros2 run {pkg} {exe} would fail"
    # package data (maps, configs) travels with the build
    site = next((colcon_install / "bimacppo_sim" / "lib").glob("python3*/site-packages"))
    assert (site / "bimacppo_sim" / "maps" / "dual_lane_4way.yaml").is_file()


def test_colcon_installed_cli_runs(colcon_install):
    exe = colcon_install / "bimacppo_sim" / "lib" / "bimacppo_sim" / "bimacppo-sim"
    site = next((colcon_install / "bimacppo_sim" / "lib").glob("python3*/site-packages"))
    env = dict(os.environ, PYTHONPATH=str(site))
    out = subprocess.run([sys.executable, str(exe), "--help"], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "render" in out.stdout and "reference" in out.stdout
