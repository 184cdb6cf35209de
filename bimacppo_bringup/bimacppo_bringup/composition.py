"""The composition of the graph, written once: which nodes run, from which executables and
classes, with which params files, shared parameters and arguments.

Two things start the graph and both read this table, so they cannot compose it differently:

* ``launch/bimacppo.launch.py`` (``ros2 launch bimacppo_bringup bimacppo.launch.py``): one process
  per node, ``package``/``executable`` of each :class:`NodeEntry`;
* ``bimacppo_bringup.graph`` (``bimacppo-graph``): every node in one process, ``node_class`` of
  each entry.

Rules:

* a node's parameters are, in this order (a later source wins): its params file's section (the
  file under ``share/<package>/config``, the section named like the node), ``SIM_TIME`` if the
  node follows the world's ``/clock``, the entry's ``fixed`` parameters, then the arguments;
* an argument's default is the value its first target has in that target's params file, so a
  default is written once (in the YAML) and an argument's type is the type of that value;
* a switch (an argument without targets) turns the nodes that name it on or off; its default is
  written here, since it is no node's parameter.

This module imports no node module (only the contract's names), so reading it builds nothing.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Mapping, Optional, Tuple

import yaml

from bimacppo_interfaces import contract as I

SIM_TIME = {"use_sim_time": True}
"""What a node that follows the world's /clock gets: ROS time is the simulated time."""


@dataclass(frozen=True)
class NodeEntry:
    name: str                       # node name, and its section in the params file
    package: str                    # ROS package of the executable
    executable: str                 # ``ros2 run <package> <executable>``
    node_class: str                 # ``module:Class`` the one-process graph builds
    params_file: Tuple[str, str]    # (package, file name under share/<package>/config)
    sim_time: bool                  # follows the world's /clock (gets SIM_TIME)
    switch: Optional[str] = None    # the switch that turns it on; None: always runs
    fixed: Mapping[str, object] = field(default_factory=dict)   # set by every composition


@dataclass(frozen=True)
class Argument:
    name: str                       # launch argument ``name:=``; graph flag ``--name`` (``_`` -> ``-``)
    help: str
    targets: Tuple[Tuple[str, str], ...] = ()   # (node, parameter) it sets; () = a switch
    default: object = None          # switches only; a parameter's default comes from its params file


# The recorder comes first: the one-process executor serves its nodes in this order, and the
# recorder must exist before the world publishes anything.
NODES: Tuple[NodeEntry, ...] = (
    NodeEntry(I.RECORDER_NODE, "bimacppo_bag", "mcap_recorder", "bimacppo_bag.recorder:McapRecorder",
              ("bimacppo_bag", "bag.params.yaml"), sim_time=False, switch="record"),
    # autostart off: the curriculum picks every episode's scenario
    NodeEntry(I.WORLD_NODE, "bimacppo_sim", "world_node", "bimacppo_sim.ros.world_node:WorldNode",
              ("bimacppo_sim", "world.params.yaml"), sim_time=False, fixed={"autostart": False}),
    NodeEntry(I.PLANNER_NODE, "bimacppo_planner", "planner_node", "bimacppo_planner.ros.planner_node:PlannerNode",
              ("bimacppo_planner", "planner.params.yaml"), sim_time=True),
    NodeEntry(I.CONTROLLER_NODE, "bimacppo_mpc", "controller_node", "bimacppo_mpc.ros.controller_node:ControllerNode",
              ("bimacppo_mpc", "controller.params.yaml"), sim_time=True),
    NodeEntry(I.CURRICULUM_NODE, "bimacppo_curriculum", "curriculum_node",
              "bimacppo_curriculum.ros.curriculum_node:CurriculumNode",
              ("bimacppo_curriculum", "curriculum.params.yaml"), sim_time=False),
    NodeEntry("live_view", "bimacppo_viz", "live_view", "bimacppo_viz.ros.live_view:LiveViewNode",
              ("bimacppo_viz", "live_view.params.yaml"), sim_time=True, switch="live_view"),
)

ARGUMENTS: Tuple[Argument, ...] = (
    Argument("episodes", "episodes to run (the curriculum stops after them; 0 = forever)",
             ((I.CURRICULUM_NODE, "episodes"),)),
    Argument("scheduler", "curriculum scheduler: bimab | fixed | random | manual | rd",
             ((I.CURRICULUM_NODE, "scheduler"),)),
    Argument("seed", "scheduler seed", ((I.CURRICULUM_NODE, "seed"),)),
    Argument("seed_base", "scenario seed of the first episode", ((I.CURRICULUM_NODE, "seed_base"),)),
    Argument("map", "road map (a map id or a YAML path) of the world, the planner and the live view",
             ((I.WORLD_NODE, "map_id"), (I.PLANNER_NODE, "map_id"), ("live_view", "map_id"))),
    Argument("slow_svs", "at most this many slow SVs per episode, drawn from the scenario seed (the "
             "overtaking protocol: 2 on three_lane_straight)", ((I.WORLD_NODE, "scenario.slow_svs"),)),
    Argument("mode", "world clock: lockstep | realtime", ((I.WORLD_NODE, "mode"),)),
    Argument("rate_factor", "realtime: sim seconds per wall second", ((I.WORLD_NODE, "rate_factor"),)),
    Argument("policy", "planner checkpoint ('': the policy shipped in bimacppo_planner)",
             ((I.PLANNER_NODE, "policy_path"),)),
    Argument("planner_class", "planner class: a bimacppo.planners entry point or module:Class",
             ((I.PLANNER_NODE, "planner_class"),)),
    Argument("solver", "MPC solver: fast | ipopt", ((I.CONTROLLER_NODE, "solver"),)),
    Argument("output", "MCAP path ('': bimacppo_<date>_<time>.mcap here)", ((I.RECORDER_NODE, "output"),)),
    Argument("port", "live view: Foxglove WebSocket port", (("live_view", "port"),)),
    Argument("record", "run the MCAP recorder", default=True),
    Argument("live_view", "serve the graph to Foxglove (bimacppo_viz, docs/live-view.md)", default=False),
)

ShareOf = Callable[[str], str]
"""package -> its share directory (``ament_index_python``'s ``get_package_share_directory``)."""


def entry(name: str) -> NodeEntry:
    for e in NODES:
        if e.name == name:
            return e
    raise KeyError(f"no node {name!r} in the composition (nodes: {[e.name for e in NODES]})")


def params_path(e: NodeEntry, share_of: ShareOf) -> str:
    pkg, name = e.params_file
    return os.path.join(share_of(pkg), "config", name)


def flatten(d: Mapping, prefix: str = "") -> Dict[str, object]:
    """Nested parameter mappings as dotted names, the way rcl reads a params file."""
    out: Dict[str, object] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def file_parameters(e: NodeEntry, share_of: ShareOf) -> Dict[str, object]:
    """The node's section of its params file, flattened to dotted names (``scenario.seed``)."""
    path = params_path(e, share_of)
    with open(path) as fh:
        doc = yaml.safe_load(fh) or {}
    section = doc.get(e.name, {}) if isinstance(doc, dict) else {}
    params = section.get("ros__parameters") if isinstance(section, dict) else None
    if not isinstance(params, dict):
        raise ValueError(f"{path}: no '{e.name}: ros__parameters:' section")
    return flatten(params)


def defaults(share_of: ShareOf) -> Dict[str, object]:
    """Every argument's default: a switch's own, else its first target's params-file value."""
    out: Dict[str, object] = {}
    for a in ARGUMENTS:
        if not a.targets:
            out[a.name] = a.default
            continue
        node, param = a.targets[0]
        values = file_parameters(entry(node), share_of)
        if param not in values:
            raise ValueError(f"argument {a.name}: {params_path(entry(node), share_of)} sets no {node}.{param}")
        out[a.name] = values[param]
    return out


def composed_parameters(e: NodeEntry, values: Mapping[str, object]) -> Dict[str, object]:
    """What the composition sets on top of the params file (SIM_TIME, fixed, arguments), in order.
    ``values`` maps argument names to values (or launch substitutions) and must name every one."""
    out: Dict[str, object] = dict(SIM_TIME) if e.sim_time else {}
    out.update(e.fixed)
    for a in ARGUMENTS:
        for node, param in a.targets:
            if node == e.name:
                out[param] = values[a.name]
    return out


def enabled(e: NodeEntry, values: Mapping[str, object]) -> bool:
    return e.switch is None or bool(values[e.switch])


def compose(values: Mapping[str, object], share_of: ShareOf) -> List[Tuple[NodeEntry, Dict[str, object]]]:
    """The running nodes and every parameter each gets (params file, then the composition)."""
    missing = [a.name for a in ARGUMENTS if a.name not in values]
    if missing:
        raise ValueError(f"no value for the arguments {missing}")
    return [(e, {**file_parameters(e, share_of), **composed_parameters(e, values)})
            for e in NODES if enabled(e, values)]

