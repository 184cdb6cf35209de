"""The curriculum node against a real world node on real DDS: it reads the world's map_tasks
and runs each arm's task through conventions.task_on_map, so on the one-task straight road
every arm runs "straight" (as in training) instead of the world refusing two arms in three.
Each episode is requested through /curriculum/next, the way a user skips one."""
import time

import pytest

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from bimacppo_common.conventions import TASKS  # noqa: E402


def _episodes_started(map_id: str, count: int, timeout_s: float = 30.0):
    """(arm task, task run, world's scenario task) of the first ``count`` episodes the
    curriculum starts on a lockstep world of ``map_id`` that nobody drives."""
    from std_srvs.srv import Trigger

    from bimacppo_curriculum.ros.curriculum_node import CurriculumNode
    from bimacppo_interfaces import contract as I
    from bimacppo_sim.ros.world_node import WorldNode

    rclpy.init()
    ex = SingleThreadedExecutor()
    nodes = []
    try:
        world = WorldNode(parameter_overrides=[Parameter("map_id", value=map_id),
                                               Parameter("autostart", value=False)])
        cur = CurriculumNode(parameter_overrides=[Parameter("episodes", value=0), Parameter("seed", value=3),
                                                  Parameter("retry_period_s", value=0.05)])
        user = Node("curriculum_user")
        nxt = user.create_client(Trigger, I.SRV_CURRICULUM_NEXT)
        nodes = [world, cur, user]
        for n in nodes:
            ex.add_node(n)
        seen = []
        t_end = time.monotonic() + timeout_s
        while len(seen) < count and time.monotonic() < t_end and not cur.done:
            ex.spin_once(timeout_sec=0.02)
            if cur.current is not None and (not seen or seen[-1][0] != cur.current):
                i, j, seed, task = cur.current
                seen.append((cur.current, (TASKS[j], task, world.world.scenario.task)))
                fut = nxt.call_async(Trigger.Request())       # abandon it: the next arm
                while not fut.done() and time.monotonic() < t_end:
                    ex.spin_once(timeout_sec=0.02)
        assert not cur.done, "the curriculum stopped"
        assert len(seen) == count, f"only {len(seen)} episodes started in {timeout_s} s"
        return [s for _, s in seen], cur.world_tasks
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()


def test_every_arm_runs_the_only_task_of_a_one_task_map():
    runs, offered = _episodes_started("three_lane_straight", 12)
    assert offered == ("straight",)
    assert all(task == "straight" and world_task == "straight" for _, task, world_task in runs), runs
    assert {arm for arm, _, _ in runs} - {"straight"}, runs     # other arms were drawn, and ran


def test_arms_run_their_own_task_where_the_map_has_it():
    runs, offered = _episodes_started("dual_lane_4way", 9)
    assert offered == TASKS
    assert all(arm == task == world_task for arm, task, world_task in runs), runs
    assert len({arm for arm, _, _ in runs}) >= 2, runs


def test_a_lost_map_tasks_request_is_asked_again():
    """A map_tasks request that never gets an answer (the world died after it was sent) must not
    hold the curriculum forever: after stall_timeout_s it asks again and starts the episode."""
    from bimacppo_curriculum.ros.curriculum_node import CurriculumNode
    from bimacppo_sim.ros.world_node import WorldNode

    rclpy.init()
    ex = SingleThreadedExecutor()
    nodes = []
    try:
        world = WorldNode(parameter_overrides=[Parameter("map_id", value="three_lane_straight"),
                                               Parameter("autostart", value=False)])
        cur = CurriculumNode(parameter_overrides=[Parameter("episodes", value=0),
                                                  Parameter("retry_period_s", value=0.05),
                                                  Parameter("stall_timeout_s", value=0.5)])
        cur._asking = True                   # as if a request had been sent and lost
        nodes = [world, cur]
        for n in nodes:
            ex.add_node(n)
        t0 = time.monotonic()
        while cur.current is None and time.monotonic() - t0 < 15.0:
            ex.spin_once(timeout_sec=0.02)
        assert cur.current is not None and cur.world_tasks == ("straight",)
        assert cur.current[3] == "straight" and time.monotonic() - t0 >= 0.5
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()


def test_a_world_without_map_tasks_is_taken_to_offer_every_task():
    """Another simulator behind the same services (scenario.* parameters, ~/reset) that declares
    no map_tasks: the curriculum asks it for every task, each arm its own."""
    from std_srvs.srv import Trigger

    from bimacppo_curriculum.ros.curriculum_node import CurriculumNode

    rclpy.init()
    ex = SingleThreadedExecutor()
    nodes = []
    try:
        other = Node("other_world")
        other.declare_parameter("scenario.n_sv", 0)
        other.declare_parameter("scenario.task", "straight")
        other.declare_parameter("scenario.seed", 0)
        resets = []

        def reset(_req, resp):
            resets.append(other.get_parameter("scenario.task").value)
            resp.success, resp.message = True, "ok"
            return resp

        other.create_service(Trigger, "~/reset", reset)
        cur = CurriculumNode(parameter_overrides=[Parameter("episodes", value=0), Parameter("seed", value=3),
                                                  Parameter("world_node", value="other_world"),
                                                  Parameter("retry_period_s", value=0.05)])
        user = Node("curriculum_user")
        nxt = user.create_client(Trigger, "/curriculum/next")
        nodes = [other, cur, user]
        for n in nodes:
            ex.add_node(n)
        arms = []
        t_end = time.monotonic() + 20.0
        while len(arms) < 9 and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.02)
            if cur.current is not None and (not arms or arms[-1][0] != cur.current):
                arms.append((cur.current, resets[-1]))
                fut = nxt.call_async(Trigger.Request())
                while not fut.done() and time.monotonic() < t_end:
                    ex.spin_once(timeout_sec=0.02)
        assert cur.world_tasks == TASKS and len(arms) == 9
        assert all(TASKS[j] == task == asked for (i, j, seed, task), asked in arms), arms
        assert len({asked for _, asked in arms}) >= 2
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()
