"""runtime.drain: after a stop request a node handles every callback already ready, however
many, and gives up on a source that never lets it become idle."""
import time

import pytest

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import Int32  # noqa: E402

from bimacppo_ros_common import runtime  # noqa: E402

DEEP = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE)


@pytest.fixture
def ctx():
    rclpy.init()
    nodes, executors = [], []

    def node(name):
        n = rclpy.create_node(name)
        nodes.append(n)
        ex = SingleThreadedExecutor()
        ex.add_node(n)
        executors.append(ex)
        return n, ex
    yield node
    for ex in executors:
        ex.shutdown()
    for n in nodes:
        n.destroy_node()
    rclpy.try_shutdown()


def test_a_drain_handles_every_message_delivered_before_the_stop(ctx):
    """400 messages wait in a subscription's queue (delivered, not yet handled), as a recorder's
    backlog does when it is stopped on a loaded machine: the drain writes all of them."""
    sink, sink_ex = ctx("drain_sink")
    probe, probe_ex = ctx("drain_probe")
    src, _ = ctx("drain_source")
    got, seen = [], []
    sink.create_subscription(Int32, "/drain_test", lambda m: got.append(m.data), DEEP)
    probe.create_subscription(Int32, "/drain_test", lambda m: seen.append(m.data), DEEP)
    pub = src.create_publisher(Int32, "/drain_test", DEEP)
    t_end = time.monotonic() + 20.0
    while pub.get_subscription_count() < 2 and time.monotonic() < t_end:
        time.sleep(0.05)
    assert pub.get_subscription_count() == 2
    for k in range(400):
        pub.publish(Int32(data=k))
    # the probe, on the same delivery path, says when DDS has handed all of them over
    while len(seen) < 400 and time.monotonic() < t_end:
        probe_ex.spin_once(timeout_sec=0.05)
    assert len(seen) == 400
    time.sleep(0.2)
    assert runtime.drain(sink_ex) is True
    assert got == list(range(400))


def test_a_drain_gives_up_on_a_source_that_never_lets_it_idle(ctx):
    """A callback that is ready again as soon as it has run (a timer slower than its period)
    would hold the stop for ever: the drain returns False at its time limit."""
    node, ex = ctx("drain_busy")
    calls = []
    node.create_timer(0.001, lambda: (calls.append(1), time.sleep(0.003)))
    time.sleep(0.01)             # the first period has passed: the timer is ready
    t0 = time.monotonic()
    assert runtime.drain(ex, timeout_s=0.3) is False
    assert 0.3 <= time.monotonic() - t0 < 5.0 and len(calls) > 10


def test_a_drain_of_an_idle_node_returns_at_once(ctx):
    node, ex = ctx("drain_idle")
    node.create_subscription(Int32, "/drain_idle", lambda m: None, DEEP)
    t0 = time.monotonic()
    assert runtime.drain(ex) is True
    assert time.monotonic() - t0 < 1.0
