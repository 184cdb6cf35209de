"""bimacppo_planner: see package.xml for what it holds. Core modules never import rclpy."""

import bimacppo_common  # noqa: F401  (before torch loads: idle OpenMP threads sleep; bimacppo_common says why)

__version__ = "0.1.0"
