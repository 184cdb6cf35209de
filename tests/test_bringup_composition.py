"""The launch file and the one-process graph compose the same graph: the same nodes, each with
the same parameters (params file, shared ``use_sim_time``, fixed values, arguments), for the
default arguments and for arguments a user gives.

The launch file is executed against minimal stand-ins of ``launch`` / ``launch_ros`` (not
installable as wheels) that record what it asks for; its parameters are then resolved the way
launch_ros does (params file section, then each dict in order, a substitution's text read as
YAML). The graph's side is what ``bimacppo-graph`` builds its nodes from.
"""
import sys
import types

import pytest
import yaml

pytest.importorskip("rclpy")

from bimacppo_bringup import composition as C  # noqa: E402
from bimacppo_bringup import graph  # noqa: E402
from conftest import REPO  # noqa: E402

LAUNCH_FILE = REPO / "bimacppo_bringup" / "launch" / "bimacppo.launch.py"


class _Rec:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


@pytest.fixture
def launch_stubs(monkeypatch):
    mods = {name: types.ModuleType(name) for name in (
        "launch", "launch.actions", "launch.conditions", "launch.substitutions", "launch_ros", "launch_ros.actions")}
    mods["launch"].LaunchDescription = lambda actions: list(actions)
    mods["launch.actions"].DeclareLaunchArgument = type("DeclareLaunchArgument", (_Rec,), {})
    mods["launch.conditions"].IfCondition = type("IfCondition", (_Rec,), {})
    mods["launch.substitutions"].LaunchConfiguration = type("LaunchConfiguration", (_Rec,), {})
    mods["launch_ros.actions"].Node = type("Node", (_Rec,), {})
    for name, mod in mods.items():
        monkeypatch.setitem(sys.modules, name, mod)
    import ament_index_python.packages as aip
    monkeypatch.setattr(aip, "get_package_share_directory", lambda pkg: str(REPO / pkg))   # source tree: config/
    return mods


def _launch_true(value) -> bool:
    """IfCondition's reading of a substitution's value (launch accepts true/false, any case)."""
    text = str(value).strip().lower()
    assert text in ("true", "false"), f"IfCondition would refuse {value!r}"
    return text == "true"


def _launched(mods, given: dict) -> dict:
    """node name -> (package, executable, parameters) of what `ros2 launch ... given` starts."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("bimacppo_launch_under_test", LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    actions = module.generate_launch_description()
    declared = {a.args[0]: a.kwargs["default_value"] for a in actions
                if isinstance(a, mods["launch.actions"].DeclareLaunchArgument)}
    assert set(given) <= set(declared), set(given) - set(declared)
    text = {**declared, **given}
    lc = mods["launch.substitutions"].LaunchConfiguration

    def value(v):
        if isinstance(v, lc):
            parsed = yaml.safe_load(text[v.args[0]])
            return "" if parsed is None else parsed
        return v

    out = {}
    for node in (a for a in actions if isinstance(a, mods["launch_ros.actions"].Node)):
        cond = node.kwargs.get("condition")
        if cond is not None and not _launch_true(value(cond.args[0])):
            continue
        params = {}
        for p in node.kwargs["parameters"]:
            if isinstance(p, str):
                section = yaml.safe_load(open(p))[node.kwargs["name"]]["ros__parameters"]
                params.update(C.flatten(section))
            else:
                params.update({k: value(v) for k, v in p.items()})
        out[node.kwargs["name"]] = (node.kwargs["package"], node.kwargs["executable"], params)
    return out


def _graphed(argv: list) -> dict:
    """node name -> (package, executable, parameters) of what `bimacppo-graph argv` builds."""
    defaults = C.defaults(graph.share_of)
    values = graph.argument_values(graph.build_parser(defaults).parse_args(argv))
    return {e.name: (e.package, e.executable, params) for e, params in C.compose(values, graph.share_of)}


CASES = [
    ({}, []),
    ({"episodes": "7", "map": "single_lane_4way", "seed_base": "5", "mode": "realtime", "rate_factor": "2.5",
      "record": "false", "live_view": "true", "port": "9001", "solver": "ipopt", "scheduler": "random"},
     ["--episodes", "7", "--map", "single_lane_4way", "--seed-base", "5", "--mode", "realtime",
      "--rate-factor", "2.5", "--no-record", "--live-view", "9001", "--solver", "ipopt", "--scheduler", "random"]),
    ({"output": "/tmp/x.mcap", "policy": "/tmp/p.pt", "seed": "3"},
     ["--output", "/tmp/x.mcap", "--policy", "/tmp/p.pt", "--seed", "3"]),
]


@pytest.mark.parametrize("given,argv", CASES)
def test_launch_file_and_graph_compose_the_same_nodes_and_parameters(launch_stubs, given, argv):
    launched, graphed = _launched(launch_stubs, given), _graphed(argv)
    assert sorted(launched) == sorted(graphed)
    for name in launched:
        assert launched[name] == graphed[name], name


def test_the_composition_sets_sim_time_autostart_and_arguments():
    default = _graphed([])
    assert sorted(default) == sorted(["mcap_recorder", "world", "planner", "controller", "curriculum"])
    for name, (_, _, params) in default.items():
        assert params.get("use_sim_time", False) is (name in ("planner", "controller")), name
    assert default["world"][2]["autostart"] is False    # the params file says true; the curriculum drives
    assert default["curriculum"][2]["episodes"] == 10   # curriculum.params.yaml's value is the default
    given = _graphed(["--map", "single_lane_4way", "--live-view", "--no-record"])
    assert "mcap_recorder" not in given and given["live_view"][2]["use_sim_time"] is True
    assert {given[n][2]["map_id"] for n in ("world", "planner", "live_view")} == {"single_lane_4way"}
    assert given["live_view"][2]["port"] == 8765        # live_view.params.yaml's port


def test_graph_refuses_an_argument_the_composition_lacks():
    defaults = C.defaults(graph.share_of)
    with pytest.raises(SystemExit):
        graph.build_parser(defaults).parse_args(["--no-such-flag", "1"])
    with pytest.raises(ValueError, match="no value for the arguments"):
        C.compose({"episodes": 1}, graph.share_of)


@pytest.mark.ros
def test_graph_nodes_run_with_the_composed_parameters(tmp_path):
    """What the graph builds carries every composed parameter (incl. use_sim_time) for real."""
    rclpy = pytest.importorskip("rclpy")
    defaults = C.defaults(graph.share_of)
    values = graph.argument_values(graph.build_parser(defaults).parse_args(
        ["--output", str(tmp_path / "run.mcap"), "--episodes", "4"]))
    rclpy.init()
    nodes = []
    try:
        nodes = graph.build_nodes(values)
        composed = {e.name: params for e, params in C.compose(values, graph.share_of)}
        assert sorted(n.get_name() for n in nodes) == sorted(composed)
        for n in nodes:
            for key, want in composed[n.get_name()].items():
                got = n.get_parameter(key).value
                assert (list(got) if isinstance(want, list) else got) == want, (n.get_name(), key)
    finally:
        from bimacppo_ros_common import runtime
        runtime.close_nodes(nodes)
        rclpy.try_shutdown()
