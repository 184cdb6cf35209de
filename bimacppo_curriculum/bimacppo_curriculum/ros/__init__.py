"""ROS 2 adapters of bimacppo_curriculum (rclpy only below this package)."""
