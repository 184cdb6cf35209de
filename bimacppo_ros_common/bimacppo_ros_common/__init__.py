"""bimacppo_ros_common: what every bimacppo node's process shares.

``runtime`` (start-up, signals, spin, clean shutdown, one-line errors), ``params`` (parameter
values and params-file checks), ``tick_protocol`` (the pure state machine of the nodes that
answer a source's ticks; no rclpy) and ``run_clock`` (a world run's clock that starts after
every earlier run's; no rclpy). It knows the contract but no role.
"""
