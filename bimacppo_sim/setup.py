"""Packaging for bimacppo_sim: an ament_python ROS 2 package that is also pip-installable.

colcon (ament_python) reads the data_files below to register the package in the
ament index and install its launch/config files under share/; pip ignores them
harmlessly when installing into a virtual environment.
"""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "bimacppo_sim"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, PACKAGE + ".*"]),
    include_package_data=True,
    package_data={PACKAGE: ["**/*.yaml", "**/*.json", "**/*.pt"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
        ("share/" + PACKAGE + "/config", glob("config/*.yaml")),
        ("share/" + PACKAGE + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=['numpy', 'pyyaml', 'matplotlib', 'imageio', 'bimacppo_common', 'bimacppo_interfaces',
                      'bimacppo_ros_common', 'bimacppo_bag'],
    zip_safe=False,
    maintainer="bimacppo maintainers",
    maintainer_email="maintainers@bimacppo.dev",
    description=open("package.xml").read().split("<description>")[1].split("</description>")[0],
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "world_node = bimacppo_sim.ros.world_node:main",
            "bimacppo-sim = bimacppo_sim.cli:main",
        ],
    },
)
