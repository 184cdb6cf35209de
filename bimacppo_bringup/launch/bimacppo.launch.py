"""Launch the whole graph as separate processes (needs a full ROS 2 install with launch_ros).

    ros2 launch bimacppo_bringup bimacppo.launch.py episodes:=10 record:=true
    ros2 launch bimacppo_bringup bimacppo.launch.py live_view:=true   # + Foxglove on ws://127.0.0.1:8765

Nodes, params files, shared parameters (``use_sim_time``) and arguments all come from
``bimacppo_bringup.composition``, the table the one-process graph
(``ros2 run bimacppo_bringup bimacppo-graph``) is built from too; an argument's default is its
params file's value.
"""
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from bimacppo_bringup import composition as C


def _text(value) -> str:
    """A default as launch writes it (launch_ros reads parameter strings as YAML)."""
    return str(value).lower() if isinstance(value, bool) else str(value)


def generate_launch_description():
    defaults = C.defaults(get_package_share_directory)
    actions = [DeclareLaunchArgument(a.name, default_value=_text(defaults[a.name]), description=a.help)
               for a in C.ARGUMENTS]
    values = {a.name: LaunchConfiguration(a.name) for a in C.ARGUMENTS}
    for e in C.NODES:
        actions.append(Node(
            package=e.package, executable=e.executable, name=e.name, output="screen",
            parameters=[C.params_path(e, get_package_share_directory), C.composed_parameters(e, values)],
            condition=IfCondition(values[e.switch]) if e.switch else None))
    return LaunchDescription(actions)
