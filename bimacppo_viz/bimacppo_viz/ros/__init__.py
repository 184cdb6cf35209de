"""ROS adapters of bimacppo_viz (the only modules here that import rclpy)."""
