"""Packaging for bimacppo_common: an ament_python ROS 2 package that is also pip-installable.

It holds what several bimacppo packages share and must stay at the bottom of the dependency
graph: it imports nothing of the other packages (and no ROS), so any of them can depend on it.
"""
from setuptools import find_packages, setup

PACKAGE = "bimacppo_common"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, PACKAGE + ".*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
    ],
    install_requires=["pyyaml"],
    zip_safe=False,
    maintainer="bimacppo maintainers",
    maintainer_email="maintainers@bimacppo.dev",
    description=open("package.xml").read().split("<description>")[1].split("</description>")[0],
    license="Apache-2.0",
    python_requires=">=3.10",
)
