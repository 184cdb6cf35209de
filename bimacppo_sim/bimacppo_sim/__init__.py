"""bimacppo_sim: the intersection world (roads, EV bicycle model, interactive SVs).

Core modules never import rclpy; the ROS node lives in ``bimacppo_sim.ros``.
"""
from .config import DriverConfig, VehicleConfig, WorldConfig
from .drivers import DRIVERS, make_driver, run_episode
from .road import RoadMap, available_maps, load_map
from .world import Scenario, StepResult, World, draw_n_slow

__version__ = "0.1.0"

__all__ = ["load_map", "World", "Scenario", "WorldConfig", "StepResult", "RoadMap",
           "VehicleConfig", "DriverConfig", "DRIVERS", "make_driver", "run_episode", "available_maps", "draw_n_slow"]
