"""Packaging for bimacppo_interfaces: an ament_python ROS 2 package that is also pip-installable.

It is the contract every node converts through. It depends only on standard message packages
(and bimacppo_common's conventions), so a node of any role, or a foreign node that speaks the
contract, can depend on it without installing another role's code.
colcon (ament_python) reads the data_files below to register the package in the ament index and
install its launch/config files under share/; pip ignores them harmlessly in a virtual environment.
"""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "bimacppo_interfaces"

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
    install_requires=['numpy', 'bimacppo_common'],
    zip_safe=False,
    maintainer="bimacppo maintainers",
    maintainer_email="maintainers@bimacppo.dev",
    description=open("package.xml").read().split("<description>")[1].split("</description>")[0],
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [],
    },
)
