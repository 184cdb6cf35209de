"""Parameter checks shared by the nodes: values in range, files that exist, params-file keys
that no node declares.

A bad value is a :class:`ConfigError` naming the node and the parameter, which ``runtime``
turns into one ``error:`` line and exit code 2; rclpy would otherwise accept it or fail later
with a traceback.
"""
from __future__ import annotations

import math
import os
from typing import List, Sequence


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


def param_range(value, name: str, node: str, lo: float = None, hi: float = None,
                lo_open: bool = False):
    """A numeric parameter within [lo, hi] (``lo_open``: strictly above lo); finite."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{node}: parameter {name} must be a number, got {value!r}") from None
    bad = not math.isfinite(v)
    if lo is not None:
        bad = bad or (v <= lo if lo_open else v < lo)
    if hi is not None:
        bad = bad or v > hi
    if bad:
        lo_s = "-inf" if lo is None else f"{lo}"
        hi_s = "inf" if hi is None else f"{hi}"
        raise ConfigError(f"{node}: parameter {name} must be in {'(' if lo_open else '['}{lo_s}, {hi_s}], "
                          f"got {value!r}")
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
