"""Launch the whole graph as separate processes (needs a full ROS 2 install with launch_ros).

    ros2 launch bimacppo_planner bimacppo.launch.py episodes:=10 record:=true
    ros2 launch bimacppo_planner bimacppo.launch.py live_view:=true   # + Foxglove on ws://127.0.0.1:8765

Parameters come from each package's config/*.params.yaml; use_sim_time follows the
world's /clock. The one-process equivalent is ``ros2 run bimacppo_planner bimacppo-graph``.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def _params(pkg, name):
    return os.path.join(get_package_share_directory(pkg), "config", name)


def generate_launch_description():
    episodes = LaunchConfiguration("episodes")
    sim = {"use_sim_time": True}
    return LaunchDescription([
        DeclareLaunchArgument("episodes", default_value="10"),
        DeclareLaunchArgument("record", default_value="true"),
        DeclareLaunchArgument("mode", default_value="lockstep"),
        DeclareLaunchArgument("live_view", default_value="false"),
        Node(package="bimacppo_sim", executable="world_node", name="world", output="screen",
             parameters=[_params("bimacppo_sim", "world.params.yaml"),
                         {"autostart": False, "mode": LaunchConfiguration("mode")}]),
        Node(package="bimacppo_planner", executable="planner_node", name="planner", output="screen",
             parameters=[_params("bimacppo_planner", "planner.params.yaml"), sim]),
        Node(package="bimacppo_mpc", executable="controller_node", name="controller", output="screen",
             parameters=[_params("bimacppo_mpc", "controller.params.yaml"), sim]),
        Node(package="bimacppo_curriculum", executable="curriculum_node", name="curriculum", output="screen",
             parameters=[_params("bimacppo_curriculum", "curriculum.params.yaml"), {"episodes": episodes}]),
        Node(package="bimacppo_sim", executable="mcap_recorder", name="mcap_recorder", output="screen",
             parameters=[_params("bimacppo_sim", "world.params.yaml")],
             condition=IfCondition(LaunchConfiguration("record"))),
        Node(package="bimacppo_viz", executable="live_view", name="live_view", output="screen",
             parameters=[_params("bimacppo_viz", "live_view.params.yaml"), sim],
             condition=IfCondition(LaunchConfiguration("live_view"))),
    ])
