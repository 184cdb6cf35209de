"""bimacppo_learning: the training stack of BiM-ACPPO (env, PPO, trainer, evaluation, experiments).

Deployment never imports this package; it imports the planner, world, controller and curriculum
cores, never their ROS nodes.
"""

__version__ = "0.1.0"
