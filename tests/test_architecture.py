"""Architecture rules (docs/architecture.md): core code never imports rclpy; the deployed
planner never imports the training stack.

Adapters live in each package's ``ros/`` subpackage; everything else is core and
must import (and be unit-testable) without a ROS installation.
"""
import ast
import pathlib
import subprocess
import sys

from conftest import REPO

PACKAGES = ["bimacppo_common", "bimacppo_sim", "bimacppo_mpc", "bimacppo_curriculum", "bimacppo_planner",
            "bimacppo_viz"]
# plain Python (no ROS package), never imported by the deployed packages
LEARNING = "bimacppo_learning"
TRAINING_ONLY = ("bimacppo_learning", "gymnasium", "tensorboard", "ray", "rliable")  # torch itself loads torch.optim


def _core_modules():
    for pkg in [*PACKAGES, LEARNING]:
        root = REPO / pkg / pkg
        for path in sorted(root.rglob("*.py")):
            rel = path.relative_to(root)
            if rel.parts[0] == "ros":
                continue
            yield pkg, path


def _imports_rclpy(path: pathlib.Path) -> bool:
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "rclpy" for a in node.names):
            return True
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "rclpy":
            return True
    return False


def test_core_sources_never_import_rclpy():
    offenders = [str(p.relative_to(REPO)) for _, p in _core_modules() if _imports_rclpy(p)]
    assert offenders == [], f"core modules importing rclpy: {offenders}"


def test_importing_every_core_module_leaves_rclpy_unloaded():
    mods = []
    for pkg, path in _core_modules():
        rel = path.relative_to(REPO / pkg).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if parts[-1] in ("__main__",):
            continue
        mods.append(".".join(parts))
    assert len(mods) >= len(PACKAGES)
    code = (
        "import importlib, sys\n"
        f"for m in {mods!r}:\n    importlib.import_module(m)\n"
        "print('LOADED' if 'rclpy' in sys.modules else 'CLEAN')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().endswith("CLEAN")


def test_every_package_is_an_ament_python_package():
    for pkg in PACKAGES:
        root = REPO / pkg
        xml = (root / "package.xml").read_text()
        assert '<package format="3">' in xml
        assert "<build_type>ament_python</build_type>" in xml
        assert (root / "resource" / pkg).exists()
        assert (root / "setup.cfg").read_text().count(f"$base/lib/{pkg}") == 2
        assert (REPO / "ros2_ws" / "src" / pkg).resolve() == root.resolve()


def test_deployed_planner_loads_no_training_code():
    """The planner node's imports (policy loading, observation, decoding) pull in nothing of
    the training stack: deploying the planner must not need gymnasium, an optimiser or the trainer."""
    code = (
        "import sys, numpy as np\n"
        "import bimacppo_planner.ros.planner_node\n"
        "from bimacppo_planner.agent import HighLevelPlanner\n"
        "hp = HighLevelPlanner.load(None)\n"
        "hp.reset(np.array([1.75, -40.0, 5.0, 1.5708]), np.array([-23.0, 5.25, 3.1416]))\n"
        "hp.step(np.array([1.75, -40.0, 5.0, 1.5708]), np.zeros((0, 4)))\n"
        f"bad = sorted(m for m in sys.modules if m.startswith({TRAINING_ONLY!r}))\n"
        "print('BAD', bad)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "BAD []", out.stdout


def test_no_package_imports_the_learning_stack_or_another_packages_node():
    offenders = []
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg / pkg).rglob("*.py")):
            tree = ast.parse(path.read_text(), filename=str(path))
            for node in ast.walk(tree):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                    [node.module or ""] if isinstance(node, ast.ImportFrom) else []
                for n in names:
                    if n.split(".")[0] == LEARNING:
                        offenders.append(f"{path.relative_to(REPO)} imports {n}")
    assert offenders == []
