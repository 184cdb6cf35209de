"""Packaging for bimacppo_learning: the training stack (plain Python, not a ROS package).

It composes the world, controller, curriculum and planner cores into a Gymnasium env, PPO, the
training loop, imitation, evaluation, reports and the experiment grid. Nothing deployed imports
it: the planner node needs only bimacppo_planner.
"""
import os
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

PACKAGE = "bimacppo_learning"
HERE = Path(__file__).resolve().parent
# Gymnasium 1.x reads no entry points, so `gym.make("bimacppo/...")` in a fresh interpreter needs
# the ids registered by an import hook; this .pth (site-packages root) installs it at start-up.
# Its one line runs _gymnasium_hook.py's source in a namespace of its own: nothing of the package
# is imported until gymnasium is.
GYM_PTH = "bimacppo_learning-gymnasium.pth"


def gymnasium_pth_line() -> str:
    source = (HERE / PACKAGE / "_gymnasium_hook.py").read_text() + "\ninstall()\n"
    return (f"import sys; exec(compile({source!r}, {GYM_PTH!r}, 'exec'), "
            f"{{'__name__': 'bimacppo_learning_gymnasium_pth'}})\n")


class build_py_with_pth(build_py):
    """build_py that also writes GYM_PTH: into build_lib for a wheel, and into the editable
    wheel's root (its install_lib) for `pip install -e`, whose build_lib is discarded."""

    def run(self):
        super().run()
        target = self.get_finalized_command("install").install_lib if self.editable_mode else self.build_lib
        os.makedirs(target, exist_ok=True)
        Path(target, GYM_PTH).write_text(gymnasium_pth_line())


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, PACKAGE + ".*"]),
    include_package_data=True,
    package_data={PACKAGE: ["**/*.yaml"]},
    install_requires=["numpy", "scipy", "torch", "gymnasium", "pyyaml", "tqdm", "matplotlib",
                      "bimacppo_common", "bimacppo_sim", "bimacppo_mpc", "bimacppo_curriculum", "bimacppo_planner"],
    zip_safe=False,
    description="Training stack of BiM-ACPPO: Gymnasium env, PPO, curricula runs, evaluation, experiments.",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "bimacppo-train = bimacppo_learning.cli:train_main",
            "bimacppo-evaluate = bimacppo_learning.cli:evaluate_main",
            "bimacppo-report = bimacppo_learning.report:main",
            "bimacppo-select = bimacppo_learning.selection:main",
            "bimacppo-experiments = bimacppo_learning.experiments:main",
            "bimacppo-imitate = bimacppo_learning.imitation:main",
        ],
    },
    cmdclass={"build_py": build_py_with_pth},
)
