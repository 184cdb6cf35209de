"""params.declare: rclpy's own ParameterDescriptor enforces ranges and read-only flags; a bad
start-up value is one ConfigError naming node and parameter."""
import math

import pytest

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from rclpy.parameter import Parameter  # noqa: E402

from bimacppo_ros_common.params import ConfigError, declare  # noqa: E402


@pytest.fixture
def make_node():
    rclpy.init()
    nodes = []

    def make(**overrides):
        node = rclpy.create_node(f"params_probe_{len(nodes)}",
                                 parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
        nodes.append(node)
        return node
    yield make
    for n in nodes:
        n.destroy_node()
    rclpy.try_shutdown()


def test_default_and_override_in_range(make_node):
    n = make_node(rate=2.5)
    assert declare(n, "rate", 1.0, "r", lo=0.01, hi=10.0) == 2.5
    assert declare(n, "depth", 10, "d", lo=1, hi=100) == 10
    d = n.describe_parameter("rate")
    assert d.read_only and d.floating_point_range[0].from_value == 0.01 and d.description == "r"
    assert n.describe_parameter("depth").integer_range[0].to_value == 100


@pytest.mark.parametrize("value", [-1.0, 10.5, math.nan, math.inf])
def test_out_of_range_start_up_value_is_one_config_error(make_node, value):
    n = make_node(rate=value)
    with pytest.raises(ConfigError, match=r"params_probe_0: parameter rate must be in \[0.01, 10.0\], got"):
        declare(n, "rate", 1.0, "r", lo=0.01, hi=10.0)


def test_choices_are_checked_and_documented(make_node):
    n = make_node(mode="fast")
    with pytest.raises(ConfigError, match="parameter mode must be one of"):
        declare(n, "mode", "lockstep", "m", choices=("lockstep", "realtime"))
    m = make_node()
    assert declare(m, "mode", "lockstep", "m", choices=("lockstep", "realtime")) == "lockstep"
    assert "realtime" in m.describe_parameter("mode").additional_constraints


def test_run_time_changes_read_only_refused_changeable_range_checked(make_node):
    n = make_node()
    declare(n, "period", 1.0, "p", lo=0.1, hi=5.0)
    declare(n, "seed", 0, "s", lo=0, hi=9, read_only=False)
    res = n.set_parameters([Parameter("period", value=2.0)])[0]
    assert not res.successful and "read-only" in res.reason and n.get_parameter("period").value == 1.0
    assert n.set_parameters([Parameter("seed", value=3)])[0].successful
    bad = n.set_parameters([Parameter("seed", value=12)])[0]
    assert not bad.successful and n.get_parameter("seed").value == 3


def test_a_range_needs_both_ends_and_a_number(make_node):
    n = make_node()
    with pytest.raises(ValueError):
        declare(n, "x", 1.0, "x", lo=0.0)
    with pytest.raises(ValueError):
        declare(n, "y", "text", "y", lo=0, hi=1)
