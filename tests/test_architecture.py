"""Architecture rules from DESIGN §2: core code never imports rclpy.

Adapters live in each package's ``ros/`` subpackage; everything else is core and
must import (and be unit-testable) without a ROS installation.
"""
import ast
import pathlib
import subprocess
import sys

from conftest import REPO

PACKAGES = ["bimacppo_sim", "bimacppo_mpc", "bimacppo_curriculum", "bimacppo_planner"]


def _core_modules():
    for pkg in PACKAGES:
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
