#!/usr/bin/env python3
"""Print docs/parameters.md: every node's parameters, from the nodes' own declarations.

Each node declares its parameters with ``bimacppo_ros_common.params.declare`` (default,
description, range or allowed values, read-only). This reads those calls from the node
modules' source (no node is built, no DDS is touched) and prints one table per node, so the
page cannot drift from the code: ``tests/test_docs_commands.py`` compares the file with this
output.

    .venv/bin/python scripts/parameter_tables.py > docs/parameters.md
"""
from __future__ import annotations

import ast
import importlib

# executable -> module defining its node
NODES = [
    ("world_node", "bimacppo_sim.ros.world_node"),
    ("planner_node", "bimacppo_planner.ros.planner_node"),
    ("controller_node", "bimacppo_mpc.ros.controller_node"),
    ("curriculum_node", "bimacppo_curriculum.ros.curriculum_node"),
    ("mcap_recorder", "bimacppo_bag.recorder"),
    ("mcap_player", "bimacppo_bag.player"),
    ("live_view", "bimacppo_viz.ros.live_view"),
]

HEADER = """# Node parameters

Generated from the nodes' declarations by `scripts/parameter_tables.py`; a test keeps this page
equal to its output. Every parameter is declared with an rclpy `ParameterDescriptor`: rclpy
refuses a value outside its range (NaN and ±inf included) or of another type, at start-up
(one `error:` line, exit code 2) and at run time; `ros2 param describe <node> <name>` shows
the same. *Read-only* parameters are read once at start-up, so a run-time change is refused
with a reason; only the world's `scenario.*` change at run time (the curriculum sets them
before each reset). Pass them as `--ros-args -p name:=value` or in a `--params-file`
(`bimacppo_*/config/*.params.yaml` hold the values the compositions use).
"""


class Computed(str):
    """A default the node computes at start-up (an expression of its own state): the table shows
    the expression."""


def _value(node, module):
    try:
        return ast.literal_eval(node)
    except (ValueError, TypeError, SyntaxError):
        pass
    try:
        return eval(compile(ast.Expression(node), "<declare>", "eval"), vars(module))  # noqa: S307 - our own source
    except NameError:
        return Computed(ast.unparse(node))


def declarations(module_name: str) -> list:
    """(name, default, description, keywords) of every ``declare(self, ...)`` call, in source
    order; a call inside ``for name, x in TABLE.items()`` gives one row per entry of TABLE."""
    module = importlib.import_module(module_name)
    tree = ast.parse(open(module.__file__).read())
    loops = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.For) and isinstance(node.target, ast.Tuple):
            for inner in ast.walk(node):
                loops[id(inner)] = node
    calls = sorted((n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
                    and n.func.id == "declare"), key=lambda n: (n.lineno, n.col_offset))
    out = []
    for call in calls:
        args = call.args[1:]
        kw = {k.arg: _value(k.value, module) for k in call.keywords}
        loop = loops.get(id(call))
        if loop is not None and isinstance(args[0], ast.Name):
            table = _value(loop.iter, module)        # TABLE.items()
            names = [t.id for t in loop.target.elts]
            for entry in table:
                env = dict(vars(module), **dict(zip(names, entry)))
                out.append(tuple(eval(compile(ast.Expression(a), "<declare>", "eval"), env)  # noqa: S307
                                 for a in args[:3]) + (kw,))
            continue
        out.append((_value(args[0], module), _value(args[1], module),
                    _value(args[2], module) if len(args) > 2 else "", kw))
    return out


def _cell(v) -> str:
    if isinstance(v, Computed):
        return f"set at start-up: `{v}`"
    if isinstance(v, bool):
        return f"`{str(v).lower()}`"
    if isinstance(v, (int, float, str)):
        return f"`{v}`" if v != "" else "(empty)"
    return "(unset)"


def table(module_name: str) -> str:
    lines = ["| parameter | default | range / values | at run time | what |", "|---|---|---|---|---|"]
    for name, default, desc, kw in declarations(module_name):
        if kw.get("lo") is not None:
            rng = f"[{kw['lo']}, {kw['hi']}]"
        elif kw.get("choices") is not None:
            rng = ", ".join(_cell(c) for c in kw["choices"])
        else:
            rng = ""
        when = "changeable" if kw.get("read_only") is False else "read-only"
        lines.append(f"| `{name}` | {_cell(default)} | {rng} | {when} | {desc.replace('|', '/')} |")
    return "\n".join(lines)


def page() -> str:
    parts = [HEADER]
    for exe, module in NODES:
        parts.append(f"## `{exe}`\n\n{table(module)}\n")
    return "\n".join(parts)


if __name__ == "__main__":
    print(page(), end="")
