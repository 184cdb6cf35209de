"""ROS 2 adapters of bimacppo_sim (rclpy lives only below this package).

``interfaces`` is the single place where topic names, QoS profiles and message
conventions are defined; every node of the stack converts through it.
"""
