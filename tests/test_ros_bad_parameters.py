"""Bad parameters end a node with one ``error:`` line and exit 2: never a traceback, never a
node that starts anyway (a busy-looping timer, an arbitrary callable behind planner_class)."""
import subprocess
import sys

import pytest

CASES = [
    ("bimacppo_curriculum.ros.curriculum_node", ["-p", "world_node:=bad name!"], "Invalid service name"),
    ("bimacppo_curriculum.ros.curriculum_node", ["-p", "result_topic:=bad topic"], "Invalid topic name"),
    ("bimacppo_bag.recorder", ["-p", "discovery_period_s:=-1.0"], "discovery_period_s must be in"),
    ("bimacppo_bag.recorder", ["-p", "flush_period_s:=0.0"], "flush_period_s must be in"),
    ("bimacppo_planner.ros.planner_node", ["-p", "planner_class:=os:system"], "is not a planner class"),
    ("bimacppo_planner.ros.planner_node", ["-p", "planner_class:=torch.serialization:load"],
     "is not a planner class"),
    ("bimacppo_planner.ros.planner_node", ["-p", "planner_class:=nonesuch"], "entry points bimacppo.planners"),
    ("bimacppo_planner.ros.planner_node", ["-p", "action_selection:=sample"], "action_selection must be one of"),
]


@pytest.mark.ros
@pytest.mark.parametrize("module, params, message", CASES)
def test_bad_parameter_is_one_error_line_and_exit_2(module, params, message, tmp_path):
    args = [str(tmp_path / "rec.mcap")] if module.endswith("recorder") else []
    out = subprocess.run([sys.executable, "-m", module, *args, "--ros-args", *params], capture_output=True,
                         text=True, timeout=120, cwd=tmp_path)
    text = out.stdout + out.stderr
    assert out.returncode == 2 and "Traceback" not in text, text
    errors = [line for line in text.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and message in errors[0], text
    assert not (tmp_path / "rec.mcap").exists()        # refused before anything was written


def test_the_default_planner_is_a_registered_planner_class():
    from bimacppo_planner.agent import HighLevelPlanner
    from bimacppo_planner.ros.planner_node import DEFAULT_CLASS, load_class

    assert load_class("default") is HighLevelPlanner is load_class(DEFAULT_CLASS)


class ArgmaxOnlyPlanner:
    """A planner class from elsewhere whose ``load`` knows nothing of action_selection."""

    @classmethod
    def load(cls, policy_path, map_id):
        return cls()

    def reset(self, ego, goal):
        pass

    def step(self, ego, svs):
        pass


def test_a_median_planner_is_built_and_a_class_that_cannot_take_it_is_refused():
    from bimacppo_planner.ros.planner_node import make_planner
    from bimacppo_ros_common.params import ConfigError

    from bimacppo_planner.agent import load_policy

    assert make_planner("default", "", "dual_lane_4way", "median").action_selection == "median"
    assert make_planner("default", "", "dual_lane_4way", "argmax").action_selection == "argmax"
    # no selection given: the file's own (the shipped default records median)
    assert make_planner("default", "", "dual_lane_4way").action_selection == load_policy().selection
    assert isinstance(make_planner(f"{__name__}:ArgmaxOnlyPlanner", "", "x"), ArgmaxOnlyPlanner)
    with pytest.raises(ConfigError, match="does not take action_selection"):
        make_planner(f"{__name__}:ArgmaxOnlyPlanner", "", "x", "median")


@pytest.mark.ros
def test_params_file_keys_no_node_declares_are_found_and_the_shipped_files_have_none(tmp_path):
    rclpy = pytest.importorskip("rclpy")
    from bimacppo_curriculum.ros.curriculum_node import CurriculumNode
    from bimacppo_mpc.ros.controller_node import ControllerNode
    from bimacppo_planner.ros.planner_node import PlannerNode
    from bimacppo_ros_common.params import undeclared_file_parameters
    from bimacppo_sim.ros.world_node import WorldNode
    from conftest import REPO

    typo = tmp_path / "typo.yaml"
    typo.write_text("controller:\n  ros__parameters:\n    watchdog_timout_s: 0.3\n    solver: fast\n"
                    "/**:\n  ros__parameters:\n    use_sim_time: false\n")
    rclpy.init()
    try:
        nodes = {"world": WorldNode(), "controller": ControllerNode(), "planner": PlannerNode(),
                 "curriculum": CurriculumNode()}
        assert undeclared_file_parameters(nodes["controller"], ["--params-file", str(typo)]) == ["watchdog_timout_s"]
        files = {"world": "bimacppo_sim", "controller": "bimacppo_mpc", "planner": "bimacppo_planner",
                 "curriculum": "bimacppo_curriculum"}
        for name, pkg in files.items():
            (shipped,) = (REPO / pkg / "config").glob("*.params.yaml")
            assert undeclared_file_parameters(nodes[name], ["--params-file", str(shipped)]) == [], shipped
        for n in nodes.values():
            n.destroy_node()
    finally:
        rclpy.try_shutdown()
