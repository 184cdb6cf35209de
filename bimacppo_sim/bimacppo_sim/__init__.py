"""bimacppo_sim: see package.xml for what it holds. Core modules never import rclpy."""

__version__ = "0.1.0"
