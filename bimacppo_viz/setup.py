"""Packaging for bimacppo_viz: an ament_python ROS 2 package that is also pip-installable.

colcon (ament_python) reads the data_files below to register the package in the ament index
and install the Foxglove layout under share/; pip ignores them harmlessly in a virtual
environment, where the layout travels as package data instead.
"""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "bimacppo_viz"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, PACKAGE + ".*"]),
    include_package_data=True,
    package_data={PACKAGE: ["layouts/*.json"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
        ("share/" + PACKAGE + "/layouts", glob(PACKAGE + "/layouts/*.json")),
        ("share/" + PACKAGE + "/config", glob("config/*.yaml")),
    ],
    install_requires=["numpy", "foxglove-sdk", "bimacppo_sim", "bimacppo_interfaces", "bimacppo_ros_common"],
    zip_safe=False,
    maintainer="bimacppo maintainers",
    maintainer_email="maintainers@bimacppo.dev",
    description=open("package.xml").read().split("<description>")[1].split("</description>")[0],
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "live_view = bimacppo_viz.ros.live_view:main",
        ],
    },
)
