"""bimacppo_bringup: how the graph is put together.

``composition`` is the one table of nodes, executables, params files, shared parameters and
arguments; the launch file (``ros2 launch bimacppo_bringup bimacppo.launch.py``) and the
one-process graph (``bimacppo-graph``, ``graph``) are both built from it, so the two cannot
compose the graph differently.
"""
