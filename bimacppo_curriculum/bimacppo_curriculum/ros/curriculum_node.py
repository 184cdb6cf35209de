"""Curriculum node: a scheduler (``make_scheduler``) choosing Omega_ij and resetting the world.

Cycle: sample (i, j) -> set the world's ``scenario.n_sv / scenario.task / scenario.seed``
through its standard SetParameters service -> call /world/reset (std_srvs/Trigger) ->
wait for the episode's result -> ``update(i, j, return)`` -> next, until ``episodes``
episodes are done (0 = forever). All service calls are asynchronous, so the node works in
a single-threaded executor next to the world it drives.

Before the first episode the node reads the world's ``map_tasks`` parameter (GetParameters) and
runs each arm's task through ``conventions.task_on_map``: on a map with one task (the straight
road) every arm runs that task, as in training; a world that does not declare ``map_tasks`` is
taken to offer all three.

The return comes from /planner/episode_result (the world's result plus the agent's
``return``, see docs/interfaces.md); ``result_topic`` can point elsewhere. Scenario seeds
are ``seed_base + episode index``: a run is reproducible from its parameters.
"""
from __future__ import annotations

import time
from collections import Counter, OrderedDict

from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_srvs.srv import Trigger

from bimacppo_common.conventions import TASKS, task_on_map
from bimacppo_curriculum import SCHEDULERS, make_scheduler
from bimacppo_interfaces import contract as I
from bimacppo_ros_common.params import declare
from bimacppo_ros_common.runtime import guarded, run_single

RECENT_TICKS = 256
"""State stamps remembered to tell a new tick from a re-send of one already seen."""


def _param(name: str, value) -> ParameterMsg:
    v = ParameterValue()
    if isinstance(value, str):
        v.type, v.string_value = ParameterType.PARAMETER_STRING, value
    else:
        v.type, v.integer_value = ParameterType.PARAMETER_INTEGER, int(value)
    return ParameterMsg(name=name, value=v)


class CurriculumNode(Node):
    """Thin adapter over ``Scheduler.sample/update``."""

    def __init__(self, **kwargs) -> None:
        super().__init__(I.CURRICULUM_NODE, **kwargs)
        scheduler = declare(self, "scheduler", "bimab", "curriculum scheduler", choices=tuple(SCHEDULERS))
        seed = declare(self, "seed", 0, "the scheduler's seed")
        self.episodes = declare(self, "episodes", 10, "episodes to run (0 = forever); BiMAB scales its "
                                "synchronisation period to it", lo=0, hi=2**31 - 1)
        self.seed_base = declare(self, "seed_base", 0, "scenario seeds are seed_base + episode index")
        result_topic = declare(self, "result_topic", I.TOPIC_PLANNER_RESULT, "episode results to learn from")
        world = declare(self, "world_node", I.WORLD_NODE, "the world node whose reset and set_parameters "
                                                          "services it calls").strip("/")
        retry = declare(self, "retry_period_s", 0.5, "period of the service-call retry loop (wall s)",
                        lo=0.01, hi=60.0)
        self.stall_timeout = declare(self, "stall_timeout_s", 5.0, "no new tick for this long (wall s): "
                                     "re-request the episode", lo=0.1, hi=3600.0)
        self.sched = make_scheduler(scheduler, seed=seed, total_episodes=self.episodes or None)
        self.cli_params = self.create_client(SetParameters, f"/{world}/set_parameters")
        self.cli_get = self.create_client(GetParameters, f"/{world}/get_parameters")
        self.world_tasks = None    # the world's map_tasks, read once before the first episode
        self._asking = False
        self.cli_reset = self.create_client(Trigger, f"/{world}/reset")
        self.dropped: dict = {}
        self.create_subscription(I.DiagnosticStatus, result_topic,
                                 guarded(self, result_topic, self._on_result, self.dropped), I.RESULT_QOS)
        self.create_service(Trigger, I.SRV_CURRICULUM_NEXT, self._on_next)
        self.done = False
        self.finished = 0
        self.counts: Counter = Counter()
        self.results = []          # (i, j, seed, outcome, return)
        self.current = None        # (i, j, seed, task run) of the running episode
        self._busy = False         # a set/reset round trip is in flight
        self._warned = False
        self._last_progress = time.monotonic()
        # progress = a state stamp not seen before: a lockstep world publishes the next tick only
        # once the current one was answered, and re-sends (with /clock) the tick nobody answers,
        # so neither /clock nor a repeated state is progress
        self._ticks: OrderedDict = OrderedDict()
        self.create_subscription(I.Odometry, I.TOPIC_EGO_ODOM,
                                 guarded(self, I.TOPIC_EGO_ODOM, self._on_state, self.dropped), I.STATE_QOS)
        self.create_timer(retry, self._kick,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))

    # ------------------------------------------------------------------ cycle
    def _on_state(self, msg) -> None:
        stamp = I.stamp_to_ns(msg.header.stamp)
        if stamp in self._ticks:
            return   # a re-send of a tick seen: the loop is not moving
        self._ticks[stamp] = None
        while len(self._ticks) > RECENT_TICKS:
            self._ticks.popitem(last=False)
        self._last_progress = time.monotonic()

    def _kick(self) -> None:
        """Start the first episode once the world's services exist (and retry failures).

        Stall recovery: a world that was killed and restarted has forgotten the episode
        (and a request sent while it was gone never gets an answer), and a loop whose
        world keeps re-sending a tick that nobody answers never ends its episode. When no
        new tick (a state stamp not seen before) came for ``stall_timeout_s`` while an
        episode or a request (map_tasks included) is outstanding, the request is dropped and
        the next episode requested again, after map_tasks is read again (a restarted world may
        serve another map).
        """
        if self.done:
            return
        if (self.current is not None or self._busy or self._asking) and \
                time.monotonic() - self._last_progress > self.stall_timeout:
            self.get_logger().warning(f"no new tick for {self.stall_timeout:g} s: requesting the episode again")
            self.current, self._busy, self._asking = None, False, False
            self.world_tasks = None        # a restarted world may serve another map: read map_tasks again
        if self.current is None and not self._busy:
            self.start_next()

    def start_next(self) -> bool:
        if self._busy or self.done:
            return False
        if not (self.cli_params.service_is_ready() and self.cli_reset.service_is_ready()
                and self.cli_get.service_is_ready()):
            return False
        if self.world_tasks is None:
            if not self._asking:
                self._asking = True
                self._last_progress = time.monotonic()   # an unanswered request counts as a stall too
                self.cli_get.call_async(GetParameters.Request(names=["map_tasks"])).add_done_callback(
                    self._after_tasks)
            return False
        self._last_progress = time.monotonic()
        i, j = self.sched.sample()
        try:
            task = task_on_map(TASKS[j], self.world_tasks)
        except ValueError as exc:
            self.done = True
            self.get_logger().error(f"arm (n_sv={i}, task={TASKS[j]}) cannot run on this world: {exc}")
            return False
        seed = self.seed_base + self.finished
        self._busy = True
        self.current = None
        req = SetParameters.Request(parameters=[
            _param("scenario.n_sv", i), _param("scenario.task", task), _param("scenario.seed", seed)])
        self.cli_params.call_async(req).add_done_callback(lambda f: self._after_params(f, (i, j, seed, task)))
        return True

    def _after_tasks(self, fut) -> None:
        """The world's map_tasks: a string array of tasks, or not declared (all three). An
        undeclared name comes back as no value (rclpy) or as a value of type NOT_SET (rclcpp)."""
        self._asking = False
        try:
            values = fut.result().values
        except Exception as exc:  # noqa: BLE001 - a failed call is retried by the timer
            self.get_logger().error(f"reading the world's map_tasks failed: {exc}")
            return
        value = values[0] if len(values) else None
        if value is None or value.type == ParameterType.PARAMETER_NOT_SET:
            self.world_tasks = TASKS
        else:
            offered = list(value.string_array_value) if value.type == ParameterType.PARAMETER_STRING_ARRAY else []
            if not offered or any(t not in TASKS for t in offered):
                self.done = True
                self.get_logger().error(f"the world's map_tasks must be a non-empty list of {TASKS}, "
                                        f"got type {value.type} {offered}")
                return
            self.world_tasks = tuple(offered)
        if len(self.world_tasks) == 1:
            self.get_logger().info(f"the world offers only the task {self.world_tasks[0]}: every arm runs it")
        self.start_next()

    def _after_params(self, fut, scen) -> None:
        try:
            results = fut.result().results
        except Exception as exc:
            self._busy = False
            self.get_logger().error(f"setting world parameters failed: {exc}")
            return
        bad = [r.reason for r in results if not r.successful]
        if bad:
            self._busy = False
            self.done = True
            self.get_logger().error(f"world rejected scenario {scen}: {bad}")
            return
        self.cli_reset.call_async(Trigger.Request()).add_done_callback(lambda f: self._after_reset(f, scen))

    def _after_reset(self, fut, scen) -> None:
        self._busy = False
        try:
            resp = fut.result()
        except Exception as exc:
            self.get_logger().error(f"/world/reset failed: {exc}")
            return
        if not resp.success:
            self.get_logger().error(f"/world/reset refused: {resp.message}")
            return
        self.current = scen
        arm = "" if scen[3] == TASKS[scen[1]] else f" (arm {TASKS[scen[1]]})"
        self.get_logger().info(f"episode {self.finished + 1}: n_sv={scen[0]} task={scen[3]}{arm} "
                               f"seed={scen[2]} ({resp.message})")

    def _on_result(self, msg) -> None:
        res = I.status_to_result(msg)
        if self.current is None:
            return
        i, j, seed, task = self.current
        if (res.n_sv, res.task, res.seed) != (i, task, seed):
            return  # a result of an abandoned episode
        self.current = None
        if res.episode_return is None:
            if not self._warned:
                self.get_logger().warning("results carry no 'return': the scheduler is not updated")
                self._warned = True
        else:
            self.sched.update(i, j, res.episode_return)
        self.finished += 1
        self.counts[res.outcome] += 1
        self.results.append((i, j, seed, res.outcome, res.episode_return))
        if self.episodes and self.finished >= self.episodes:
            self.done = True
            self.get_logger().info(f"curriculum done: {dict(self.counts)}")
            return
        self.start_next()

    def _on_next(self, _req, resp):
        if self.done:
            resp.success, resp.message = False, "curriculum finished"
        elif self.start_next():
            resp.success, resp.message = True, "next scenario requested"
        else:
            resp.success, resp.message = False, "busy or world services not available"
        return resp


def main(argv=None) -> int:
    def make(args):
        if args:
            raise ValueError(f"curriculum_node takes no positional arguments (got {args})")
        return CurriculumNode()
    return run_single(make, argv)


if __name__ == "__main__":
    raise SystemExit(main())
