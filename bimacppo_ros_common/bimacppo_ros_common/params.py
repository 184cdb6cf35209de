"""Node parameters: declared with rclpy's ``ParameterDescriptor`` (ranges, read-only flags,
descriptions), files that exist, params-file keys that no node declares.

Every node declares its parameters through :func:`declare`, so the rules live in the
descriptor where ROS tools see them (``ros2 param describe``) and rclpy enforces them: a value
outside its range is refused at start-up and at run time, and a read-only parameter (read
once at start-up) refuses a run-time change with a reason instead of accepting and ignoring it.
A bad start-up value is a :class:`ConfigError` naming the node and the parameter, which
``runtime`` turns into one ``error:`` line and exit code 2.
"""
from __future__ import annotations

import os
from typing import List, Optional, Sequence


class ConfigError(ValueError):
    """A start-up problem the user must fix (bad parameter, unreadable file)."""


def param_file(value: str, name: str, node: str) -> str:
    """A parameter that names a file: it must exist and be a regular file."""
    path = str(value)
    if not os.path.exists(path):
        raise ConfigError(f"{node}: parameter {name}: no such file: {path!r}")
    if not os.path.isfile(path):
        raise ConfigError(f"{node}: parameter {name}: not a regular file: {path!r}")
    return path


def descriptor(default, description: str, lo=None, hi=None, choices: Optional[Sequence[str]] = None,
               read_only: bool = True):
    """The ``ParameterDescriptor`` of a parameter: a ``FloatingPointRange`` or ``IntegerRange``
    [lo, hi] (both ends, inclusive, as ROS ranges are) for a number, the allowed values of a
    string in ``additional_constraints``."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

    d = ParameterDescriptor(description=description, read_only=read_only)
    if (lo is None) != (hi is None):
        raise ValueError("descriptor: give both lo and hi, or neither")
    if lo is not None:
        if isinstance(default, bool) or not isinstance(default, (int, float)):
            raise ValueError(f"descriptor: a range needs a numeric default, got {default!r}")
        if isinstance(default, int):
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
        d.additional_constraints = f"in [{lo}, {hi}]"
    if choices is not None:
        d.additional_constraints = "one of: " + ", ".join(map(str, choices))
    return d


def declare(node, name: str, default, description: str, lo=None, hi=None,
            choices: Optional[Sequence[str]] = None, read_only: bool = True):
    """Declare ``name`` with its descriptor and return its value (the override, else ``default``).

    ``read_only`` (the default): the node reads it once at start-up, so a run-time change is
    refused by rclpy. ``choices``: the value must be one of them (checked here at start-up;
    a run-time changeable parameter checks it again in the node's set-parameters callback)."""
    from rclpy.exceptions import InvalidParameterValueException

    try:
        value = node.declare_parameter(name, default, descriptor(default, description, lo, hi, choices,
                                                                 read_only)).value
    except InvalidParameterValueException as exc:
        got = str(exc).split("Invalid parameter value (", 1)[-1].split(") for parameter", 1)[0]
        raise ConfigError(f"{node.get_name()}: parameter {name} must be in [{lo}, {hi}], got {got}") from None
    if choices is not None and value not in choices:
        raise ConfigError(f"{node.get_name()}: parameter {name} must be one of {tuple(choices)}, got {value!r}")
    return value


def undeclared_file_parameters(node, argv: Sequence[str]) -> List[str]:
    """Keys that a ``--params-file`` of ``argv`` gives this node but the node never declared.
    rclpy ignores them without a word, so a misspelt key (``watchdog_timout_s``) would leave the
    default in force unnoticed."""
    import yaml

    def flat(d, prefix=""):
        for k, v in d.items():
            if isinstance(v, dict):
                yield from flat(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}"

    args = list(argv)
    files = [args[i + 1] for i, a in enumerate(args[:-1]) if a == "--params-file"]
    me = {node.get_name(), "/" + node.get_name(), node.get_fully_qualified_name(), "/**"}
    found = set()
    for f in files:
        try:
            with open(f) as fh:
                doc = yaml.safe_load(fh) or {}
        except (OSError, yaml.YAMLError):  # rcl already parsed (or refused) the file at init
            continue
        for key, section in (doc.items() if isinstance(doc, dict) else []):
            if key in me and isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
                found |= set(flat(section["ros__parameters"]))
    return sorted(n for n in found if not node.has_parameter(n))


def warn_undeclared_file_parameters(node, argv: Sequence[str]) -> List[str]:
    """One warning per key of the params file that is not a parameter of ``node`` (with the
    nearest declared name); returns the keys."""
    import difflib

    unknown = undeclared_file_parameters(node, argv)
    declared = list(node.list_parameters([], 0).names)
    for name in unknown:
        near = difflib.get_close_matches(name, declared, n=1)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        node.get_logger().warning(f"params file sets {name!r}, which is not a parameter of this node{hint}: ignored")
    return unknown
