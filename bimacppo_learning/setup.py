"""Packaging for bimacppo_learning: the training stack (plain Python, not a ROS package).

It composes the world, controller, curriculum and planner cores into a Gymnasium env, PPO, the
training loop, imitation, evaluation, reports and the experiment grid. Nothing deployed imports
it: the planner node needs only bimacppo_planner.
"""
from setuptools import find_packages, setup

PACKAGE = "bimacppo_learning"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, PACKAGE + ".*"]),
    include_package_data=True,
    package_data={PACKAGE: ["**/*.yaml"]},
    install_requires=["numpy", "torch", "gymnasium", "pyyaml", "tqdm", "matplotlib",
                      "bimacppo_sim", "bimacppo_mpc", "bimacppo_curriculum", "bimacppo_planner"],
    zip_safe=False,
    description="Training stack of BiM-ACPPO: Gymnasium env, PPO, curricula runs, evaluation, experiments.",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "bimacppo-train = bimacppo_learning.cli:train_main",
            "bimacppo-evaluate = bimacppo_learning.cli:evaluate_main",
            "bimacppo-report = bimacppo_learning.report:main",
            "bimacppo-experiments = bimacppo_learning.experiments:main",
            "bimacppo-imitate = bimacppo_learning.imitation:main",
        ],
        "gymnasium.envs": ["bimacppo = bimacppo_learning.env:register_envs"],
    },
)
