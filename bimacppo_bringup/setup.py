"""Packaging for bimacppo_bringup: an ament_python ROS 2 package that is also pip-installable.

It is the top of the dependency graph: the only package that knows every node, so it is the
only one that may import another package's node module.
colcon (ament_python) reads the data_files below to register the package in the ament index and
install its launch/config files under share/; pip ignores them harmlessly in a virtual environment.
"""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "bimacppo_bringup"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, PACKAGE + ".*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
        ("share/" + PACKAGE + "/config", glob("config/*.yaml")),
        ("share/" + PACKAGE + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=['pyyaml', 'bimacppo_common', 'bimacppo_interfaces', 'bimacppo_ros_common', 'bimacppo_sim',
                      'bimacppo_planner', 'bimacppo_mpc', 'bimacppo_curriculum', 'bimacppo_bag', 'bimacppo_viz'],
    zip_safe=False,
    maintainer="bimacppo maintainers",
    maintainer_email="maintainers@bimacppo.dev",
    description=open("package.xml").read().split("<description>")[1].split("</description>")[0],
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "bimacppo-graph = bimacppo_bringup.graph:main",
        ],
    },
)
