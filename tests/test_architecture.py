"""Architecture rules (docs/architecture.md).

* Role packages (world, controller, curriculum, planner, viewer) keep their ROS adapters in
  ``ros/``; everything else in them is core and never imports rclpy. The ROS-layer packages
  (contract, node plumbing, bag tools, bringup) are ROS by purpose; their pure modules stay pure.
* The package dependency graph (package.xml ``exec_depend`` between bimacppo packages) is a DAG,
  every import of another bimacppo package is declared there, and setup.py asks pip for the same.
* The controller and the curriculum install no simulator; the contract package imports only
  standard message packages (and bimacppo_common).
* No package imports another package's node module, except bimacppo_bringup, whose purpose is
  to compose the nodes; no deployed package imports the training stack.
"""
import ast
import pathlib
import re
import subprocess
import sys
import xml.etree.ElementTree as ET

from conftest import REPO

# role packages: core + ros/ adapters
ROLE_PACKAGES = ["bimacppo_common", "bimacppo_sim", "bimacppo_mpc", "bimacppo_curriculum", "bimacppo_planner",
                 "bimacppo_viz"]
# the ROS layer, split like navigation2's nav2_msgs / nav2_ros_common / nav2_bringup
ROS_LAYER = ["bimacppo_interfaces", "bimacppo_ros_common", "bimacppo_bag", "bimacppo_bringup"]
PACKAGES = ROLE_PACKAGES + ROS_LAYER
PURE_ROS_LAYER_MODULES = ["bimacppo_ros_common/tick_protocol.py", "bimacppo_ros_common/run_clock.py",
                          "bimacppo_bag/mcap_io.py"]
# plain Python (no ROS package), never imported by the deployed packages
LEARNING = "bimacppo_learning"
TRAINING_ONLY = ("bimacppo_learning", "gymnasium", "tensorboard", "ray", "rliable")  # torch itself loads torch.optim
COMPOSER = "bimacppo_bringup"
# what the contract may import: the standard library, numpy, rclpy's QoS, standard message packages
CONTRACT = "bimacppo_interfaces"
STD_MESSAGE_PACKAGES = {"builtin_interfaces", "diagnostic_msgs", "geometry_msgs", "nav_msgs", "rosgraph_msgs",
                        "std_msgs", "trajectory_msgs", "visualization_msgs"}
CONTRACT_MAY_IMPORT = STD_MESSAGE_PACKAGES | {"numpy", "rclpy", "bimacppo_common"}
NO_SIMULATOR = ["bimacppo_mpc", "bimacppo_curriculum"]


def _sources(pkg):
    root = REPO / pkg / pkg
    return sorted(root.rglob("*.py"))


def _core_modules():
    for pkg in [*ROLE_PACKAGES, LEARNING]:
        root = REPO / pkg / pkg
        for path in _sources(pkg):
            if path.relative_to(root).parts[0] == "ros":
                continue
            yield pkg, path
    for rel in PURE_ROS_LAYER_MODULES:
        pkg = rel.split("/")[0]
        yield pkg, REPO / pkg / rel


def _imported(path: pathlib.Path):
    """Every module name an import statement of the file names (lazy imports included);
    relative imports resolved against the file's package."""
    tree = ast.parse(path.read_text(), filename=str(path))
    pkg_parts = list(path.relative_to(REPO).parts[1:-1])   # <pkg>/<pkg>/a/b.py -> [<pkg>, a]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg_parts[:len(pkg_parts) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            yield mod
            for a in node.names:   # ``from pkg import module`` imports pkg.module
                yield f"{mod}.{a.name}"


def _top(name: str) -> str:
    return name.split(".")[0]


def _declared(pkg: str) -> set:
    root = ET.parse(REPO / pkg / "package.xml").getroot()
    return {e.text.strip() for e in root.iter() if e.tag in ("exec_depend", "depend") and e.text}


def _bimacppo_deps(pkg: str) -> set:
    return {d for d in _declared(pkg) if d.startswith("bimacppo_")}


def _closure(pkg: str) -> set:
    seen, todo = set(), [pkg]
    while todo:
        for d in _bimacppo_deps(todo.pop()):
            if d not in seen:
                seen.add(d)
                todo.append(d)
    return seen


def _node_modules() -> dict:
    """module name -> package, for every module that defines an rclpy Node subclass."""
    out = {}
    for pkg in PACKAGES:
        for path in _sources(pkg):
            tree = ast.parse(path.read_text(), filename=str(path))
            if any(isinstance(n, ast.ClassDef) and any(getattr(b, "id", getattr(b, "attr", None)) == "Node"
                                                       for b in n.bases) for n in tree.body):
                rel = path.relative_to(REPO / pkg).with_suffix("")
                out[".".join(rel.parts)] = pkg
    return out


def test_core_sources_never_import_rclpy():
    offenders = [str(p.relative_to(REPO)) for _, p in _core_modules() if any(_top(m) == "rclpy" for m in _imported(p))]
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
    assert len(mods) >= len(ROLE_PACKAGES)
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
    install = (REPO / "scripts" / "install.sh").read_text()
    for pkg in PACKAGES:
        assert f'-e "$ROOT/{pkg}"' in install, f"scripts/install.sh does not install {pkg}"
        assert f"COPY {pkg} src/{pkg}" in (REPO / "docker" / "Dockerfile").read_text(), pkg


def test_package_dependencies_form_a_dag_that_declares_every_import():
    deps = {pkg: _bimacppo_deps(pkg) for pkg in PACKAGES}
    assert all(d in PACKAGES for ds in deps.values() for d in ds), deps
    order, left = [], dict(deps)
    while left:   # Kahn: a package whose dependencies are all placed is next
        ready = sorted(p for p, ds in left.items() if ds <= set(order))
        assert ready, f"dependency cycle among {sorted(left)}"
        order += ready
        for p in ready:
            del left[p]
    undeclared = []
    for pkg in PACKAGES:
        for path in _sources(pkg):
            for mod in {_top(m) for m in _imported(path)}:
                if mod.startswith("bimacppo_") and mod != pkg and mod not in deps[pkg]:
                    undeclared.append(f"{path.relative_to(REPO)} imports {mod}, not an exec_depend of {pkg}")
    assert undeclared == []


def test_setup_py_requires_the_bimacppo_packages_package_xml_declares():
    for pkg in PACKAGES:
        text = (REPO / pkg / "setup.py").read_text()
        m = re.search(r"install_requires\s*=\s*(\[[^\]]*\])", text)
        assert m, f"{pkg}/setup.py has no install_requires list"
        required = {r for r in ast.literal_eval(m.group(1)) if r.startswith("bimacppo_")}
        assert required == _bimacppo_deps(pkg), pkg


def test_controller_and_curriculum_install_no_simulator():
    for pkg in NO_SIMULATOR:
        assert _closure(pkg) <= {"bimacppo_common", "bimacppo_interfaces", "bimacppo_ros_common"}, (pkg, _closure(pkg))
    code = ("import sys\nimport bimacppo_mpc.ros.controller_node, bimacppo_curriculum.ros.curriculum_node\n"
            "print('LOADED', sorted(m for m in sys.modules if m.startswith(('bimacppo_sim', 'bimacppo_bag', "
            "'bimacppo_planner', 'bimacppo_bringup'))))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "LOADED []", out.stdout


def test_the_contract_imports_only_standard_message_packages():
    assert _bimacppo_deps(CONTRACT) <= {"bimacppo_common"}
    found = set()
    for path in _sources(CONTRACT):
        found |= {_top(m) for m in _imported(path)}
    foreign = sorted(m for m in found if m not in CONTRACT_MAY_IMPORT and m != CONTRACT
                     and m not in sys.stdlib_module_names)
    assert foreign == [], f"{CONTRACT} imports {foreign}"
    declared_msgs = {d for d in _declared(CONTRACT) if d.endswith("_msgs") or d == "builtin_interfaces"}
    assert declared_msgs <= STD_MESSAGE_PACKAGES


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
    nodes = _node_modules()
    assert {"bimacppo_sim.ros.world_node", "bimacppo_mpc.ros.controller_node", "bimacppo_bag.recorder",
            "bimacppo_viz.ros.live_view"} <= set(nodes), nodes
    offenders = []
    for pkg in PACKAGES:
        for path in _sources(pkg):
            for name in set(_imported(path)):
                if _top(name) == LEARNING:
                    offenders.append(f"{path.relative_to(REPO)} imports {name}")
                if pkg != COMPOSER and nodes.get(name, pkg) != pkg:
                    offenders.append(f"{path.relative_to(REPO)} imports {name}, a node of {nodes[name]}")
    assert offenders == []
