"""ROS 2 adapters of bimacppo_mpc (rclpy only below this package)."""
