"""ROS 2 adapters of bimacppo_planner (rclpy only below this package)."""
