"""The world node, the ROS 2 adapter of bimacppo_sim (rclpy lives only below this package).

It speaks the contract of bimacppo_interfaces and runs on bimacppo_ros_common's plumbing.
"""
