"""The commands the docs show exist as written, so the docs cannot drift from the code.

For every command in the fenced shell blocks of README.md, docs/ros.md and docs/live-view.md:

* a console script is an entry point of one of the project's packages (``ros2 run PKG EXE``:
  of package PKG); a script path (``scripts/demo.sh``, ``python scripts/x.py``) exists;
* an argparse CLI accepts every ``--flag`` / ``-f`` given, in the (sub)parser the command line
  reaches (the parser is captured at its first parse, so nothing runs);
* a ROS node executable takes no flags of its own; each ``-p NAME:=…`` after ``--ros-args`` is a
  parameter the node declares, each ``--params-file`` exists;
* ``ros2 launch PKG FILE ARG:=…``: the launch file exists and every argument is one of the
  composition's.

In the prose of docs/ros.md, ``NAME:=value`` names a declared parameter of some node or a launch
argument, and ``NAME`` = number states that parameter's default. A parameter table (first column
``parameter``) lists exactly the declared parameters of its node, and a default written as one
literal equals the node's params YAML; a params YAML sets only declared parameters, each to its
declared default. The bag tools refuse an option for a file name. Declared parameters are read from the node modules'
source (``declare_parameter`` calls), so no node is built and no DDS is touched.
"""
from __future__ import annotations

import argparse
import ast
import importlib.util
import os
import re
import shlex
import sys
from importlib import metadata
from pathlib import Path

import pytest

from conftest import REPO, load_script

DOCS = ("README.md", "docs/ros.md", "docs/live-view.md")
PROSE_DOCS = ("docs/ros.md",)
PARAMETER_TABLES = {"docs/live-view.md": "live_view"}   # doc -> the composition node its table describes
EXTERNAL = {"export", "cd", "source", "colcon", "tensorboard", "docker", "ray"}   # not ours to check
ROS_PARAM_ARGS = {"-p", "--param"}
ROS_FILE_ARGS = {"--params-file"}
ROS_OTHER_ARGS = {"-r", "--remap", "--log-level", "-e", "--enclave"}
SEPARATORS = {"&", "&&", "||", "|", ";"}
PLACEHOLDERS = {"...", "…"}
FENCE = re.compile(r"^```(\w*)\s*$")
SHELL_LANGS = {"bash", "sh", "shell", "console", ""}


# ----------------------------------------------------------------------------- the docs' commands
def shell_blocks(text: str):
    """(first line number, lines) of every fenced shell block."""
    out, block, start = [], None, 0
    for i, line in enumerate(text.splitlines(), 1):
        m = FENCE.match(line.strip())
        if block is None and m and m.group(1) in SHELL_LANGS:
            block, start = [], i + 1
        elif block is not None and line.strip().startswith("```"):
            out.append((start, block))
            block = None
        elif block is not None:
            block.append(line)
    return out


def commands(lines, first_line: int):
    """(line number, tokens) per simple command; comments dropped, continuations joined."""
    joined, buf, at = [], "", first_line
    for i, line in enumerate(lines, first_line):
        if not buf:
            at = i
        if line.rstrip().endswith("\\"):
            buf += line.rstrip()[:-1] + " "
            continue
        joined.append((at, buf + line))
        buf = ""
    for at, line in joined:
        lex = shlex.shlex(line, posix=True, punctuation_chars=True)
        lex.whitespace_split = True
        cmd = []
        for tok in lex:
            if tok in SEPARATORS:
                if cmd:
                    yield at, cmd
                cmd = []
            elif tok not in PLACEHOLDERS:
                cmd.append(tok)
        if cmd:
            yield at, cmd


def doc_commands():
    for doc in DOCS:
        for first, lines in shell_blocks((REPO / doc).read_text()):
            yield doc, first, list(commands(lines, first))


# ----------------------------------------------------------------------------- the code's facts
def console_scripts() -> dict:
    """script name -> (distribution name with '_', 'module:function') of the project's packages."""
    out = {}
    for ep in metadata.entry_points(group="console_scripts"):
        dist = ep.dist.name.replace("-", "_") if ep.dist is not None else ""
        if dist.startswith("bimacppo"):
            out[ep.name] = (dist, ep.value)
    return out


def module_file(module: str) -> Path:
    spec = importlib.util.find_spec(module)
    assert spec is not None and spec.origin, f"module {module} not found"
    return Path(spec.origin)


def _literal(node):
    try:
        return ast.literal_eval(node)
    except (ValueError, TypeError, SyntaxError):
        return None


def declared_parameters(module: str) -> dict:
    """name -> default (None when neither a literal nor a module-level name) of every ``declare_parameter`` call in the
    module: direct calls, ``params.declare(self, name, default, ...)``, calls through an alias (``d = self.declare_parameter``), and calls in
    a loop over a module-level dict literal of names (``for name, topic in TABLE.items()``)."""
    tree = ast.parse(module_file(module).read_text())
    tables = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Dict):
            keys = [_literal(k) for k in node.value.keys]
            if keys and all(isinstance(k, str) for k in keys):
                for t in node.targets:
                    if isinstance(t, ast.Name):
                        tables[t.id] = keys
    aliases = {"declare_parameter", "declare"}
    for node in ast.walk(tree):
        if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Attribute)
                and node.value.attr == "declare_parameter"):
            aliases |= {t.id for t in node.targets if isinstance(t, ast.Name)}
    loop_names = {}   # loop variable -> the names it takes
    for node in ast.walk(tree):
        if isinstance(node, ast.For):
            it = node.iter
            if isinstance(it, ast.Call) and isinstance(it.func, ast.Attribute) and it.func.attr in ("items", "keys"):
                it = it.func.value
            if isinstance(it, ast.Name) and it.id in tables:
                target = node.target.elts[0] if isinstance(node.target, ast.Tuple) else node.target
                if isinstance(target, ast.Name):
                    loop_names[target.id] = tables[it.id]
    out = {}
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and node.args):
            continue
        f = node.func
        name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
        if name not in aliases:
            continue
        args = node.args
        if name == "declare":   # params.declare(node, name, default, description, ...)
            args = args[1:]
            if not args:
                continue
        first = args[0]
        default = _literal(args[1]) if len(args) > 1 else None
        if default is None and len(args) > 1 and isinstance(args[1], ast.Name):
            # a named constant (``MAX_STAMP_JUMP_S``): its value in the imported module
            default = getattr(importlib.import_module(module), args[1].id, None)
        if isinstance(first, ast.Constant) and isinstance(first.value, str):
            out[first.value] = default
        elif isinstance(first, ast.Name) and first.id in loop_names:
            out.update({n: None for n in loop_names[first.id]})
    return out


def is_node_executable(target: str) -> bool:
    """An executable whose ``main`` is a node's (``runtime.run_single``): it takes ROS args only."""
    module = target.split(":")[0]
    return "run_single(" in module_file(module).read_text()


class _Captured(Exception):
    def __init__(self, parser):
        super().__init__("captured")
        self.parser = parser


def argparse_parser(monkeypatch, target: str = None, script: Path = None) -> argparse.ArgumentParser:
    """The parser a CLI builds, captured at its first parse (the CLI itself never runs).
    ``monkeypatch`` keeps ``parse_known_args`` replaced until the test ends."""
    import runpy

    def capture(self, args=None, namespace=None):
        raise _Captured(self)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", capture)
    monkeypatch.setattr(sys, "argv", ["prog"])
    try:
        if script is not None:
            runpy.run_path(str(script), run_name="__main__")
        else:
            module, func = target.split(":")
            fn = getattr(__import__(module, fromlist=[func]), func)
            if "argv" in fn.__code__.co_varnames[:fn.__code__.co_argcount]:
                fn([])
            else:
                fn()
    except _Captured as cap:
        return cap.parser
    raise AssertionError(f"{target or script} parsed no arguments")


def _options(parser) -> set:
    return {s for a in parser._actions for s in a.option_strings}


def _subparsers(parser) -> dict:
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            return dict(a.choices)
    return {}


def argparse_problems(parser, args) -> list:
    """Flags the parser (or the sub-parser the arguments select) does not accept."""
    problems, allowed, sub = [], _options(parser), _subparsers(parser)
    for tok in args:
        if tok == "--ros-args":
            break
        if re.match(r"^--?[A-Za-z]", tok):
            flag = tok.split("=", 1)[0]
            if flag not in allowed:
                problems.append(f"unknown flag {flag}")
        elif tok in sub:
            parser = sub[tok]
            allowed, sub = allowed | _options(parser), _subparsers(parser)
    return problems


def composition():
    from bimacppo_bringup import composition as C
    return C


# ----------------------------------------------------------------------------- checking one command
class Checker:
    def __init__(self, monkeypatch):
        self.monkeypatch = monkeypatch
        self.scripts = console_scripts()
        self._parsers = {}

    def parser(self, key, **kw):
        if key not in self._parsers:
            self._parsers[key] = argparse_parser(self.monkeypatch, **kw)
        return self._parsers[key]

    def ros_args(self, target: str, args, cwd: Path) -> list:
        if "--ros-args" not in args:
            return []
        problems, declared = [], declared_parameters(target.split(":")[0])
        rest = args[args.index("--ros-args") + 1:]
        i = 0
        while i < len(rest):
            tok = rest[i]
            value = rest[i + 1] if i + 1 < len(rest) else None
            if tok in ROS_PARAM_ARGS:
                name = (value or "").split(":=", 1)[0]
                if name not in declared:
                    problems.append(f"-p {name}: not a parameter of {target} (declared: {sorted(declared)})")
                i += 2
            elif tok in ROS_FILE_ARGS:
                if value is None or not (cwd / value).is_file():
                    problems.append(f"--params-file {value}: no such file (from {cwd.relative_to(REPO)})")
                i += 2
            elif tok in ROS_OTHER_ARGS:
                i += 2
            else:
                problems.append(f"unexpected ROS argument {tok!r}")
                i += 1
        return problems

    def script(self, name: str, args, cwd: Path) -> list:
        if name not in self.scripts:
            return [f"{name}: no console script of that name (known: {sorted(self.scripts)})"]
        target = self.scripts[name][1]
        own = args[:args.index("--ros-args")] if "--ros-args" in args else list(args)
        if is_node_executable(target):
            problems = [f"{name} is a node: flag {t} is not a ROS argument" for t in own if t.startswith("-")]
        else:
            problems = [f"{name}: {p}" for p in argparse_problems(self.parser(name, target=target), own)]
        return problems + [f"{name}: {p}" for p in self.ros_args(target, args, cwd)]

    def ros2(self, args, cwd: Path) -> list:
        verb = args[0] if args else ""
        if verb == "run":
            pkg, exe, rest = args[1], args[2], args[3:]
            if self.scripts.get(exe, ("",))[0] != pkg:
                return [f"ros2 run {pkg} {exe}: {exe} is no executable of {pkg}"]
            return self.script(exe, rest, cwd)
        if verb == "launch":
            pkg, launch_file, rest = args[1], args[2], args[3:]
            problems = [] if (REPO / pkg / "launch" / launch_file).is_file() else [
                f"ros2 launch {pkg} {launch_file}: no such launch file"]
            names = {a.name for a in composition().ARGUMENTS}
            for tok in rest:
                if ":=" in tok and tok.split(":=")[0] not in names:
                    problems.append(f"ros2 launch: no argument {tok.split(':=')[0]!r} (arguments: {sorted(names)})")
            return problems
        if verb == "bag":
            return []
        return [f"ros2 {verb}: not a verb the docs are expected to use"]

    def command(self, tokens, cwd: Path):
        """(problems, new cwd)."""
        while tokens and re.match(r"^[A-Z_][A-Z0-9_]*=", tokens[0]):   # VAR=value prefixes
            tokens = tokens[1:]
        if not tokens:
            return [], cwd
        cmd, args = tokens[0], tokens[1:]
        if cmd.startswith(".venv/bin/"):
            cmd = cmd[len(".venv/bin/"):]
        if cmd == "cd":
            return [], cwd / args[0]
        if cmd in EXTERNAL:
            return [], cwd
        if cmd == "ros2":
            return self.ros2(args, cwd), cwd
        if cmd in ("python", "python3"):
            if args and args[0].endswith(".py"):
                path = cwd / args[0]
                if not path.is_file():
                    return [f"{args[0]}: no such script"], cwd
                parser = self.parser(str(path), script=path)
                return [f"{args[0]}: {p}" for p in argparse_problems(parser, args[1:])], cwd
            return [], cwd      # python -c / -m: not a command of ours
        if "/" in cmd:
            return ([] if (cwd / cmd).is_file() else [f"{cmd}: no such script"]), cwd
        return self.script(cmd, args, cwd), cwd


@pytest.fixture
def checker(monkeypatch):
    monkeypatch.setenv("AMENT_PREFIX_PATH", os.environ.get("AMENT_PREFIX_PATH", sys.prefix))
    return Checker(monkeypatch)


def test_every_documented_command_exists_with_its_flags_and_parameters(checker):
    problems, seen = [], 0
    for doc, _, cmds in doc_commands():
        cwd = REPO      # each block starts at the repository root; a `cd` holds for its block
        for line, tokens in cmds:
            found, cwd = checker.command(tokens, cwd)
            seen += 1
            problems += [f"{doc}:{line}: {p}" for p in found]
    assert seen > 30, f"only {seen} commands found: the block parser lost some"
    assert not problems, "\n".join(problems)


# ----------------------------------------------------------------------------- prose and tables
def all_declared() -> dict:
    """parameter -> {node module: default} over every node executable of the project."""
    out = {}
    for name, (_, target) in console_scripts().items():
        if is_node_executable(target):
            module = target.split(":")[0]
            for p, default in declared_parameters(module).items():
                out.setdefault(p, {})[module] = default
    return out


def test_parameters_named_in_the_prose_exist_with_the_stated_defaults():
    declared = all_declared()
    launch_args = {a.name for a in composition().ARGUMENTS}
    problems, checked = [], 0
    for doc in PROSE_DOCS:
        text = (REPO / doc).read_text()
        for m in re.finditer(r"`([a-z_][a-z0-9_.]*):=[^`]*`", text):
            checked += 1
            if m.group(1) not in declared and m.group(1) not in launch_args:
                problems.append(f"{doc}: `{m.group(0)}`: no node declares {m.group(1)!r} and no launch argument")
        for m in re.finditer(r"`([a-z_][a-z0-9_.]*)` = ([0-9][0-9.]*)", text):
            name, value = m.group(1), float(m.group(2).rstrip("."))
            if name not in declared:
                continue     # a constant of the code (e.g. a module attribute), not a parameter
            checked += 1
            defaults = {d for d in declared[name].values() if isinstance(d, (int, float))}
            if value not in defaults:
                problems.append(f"{doc}: `{name}` = {m.group(2)}, but its default is {sorted(defaults)}")
    assert checked >= 10, checked
    assert not problems, "\n".join(problems)


def test_console_scripts_named_in_the_prose_exist():
    scripts = console_scripts()
    pattern = re.compile(r"`(bimacppo-[a-z-]+|[a-z]+_node|mcap_recorder|mcap_player|live_view)[` ]")
    named = {m.group(1) for doc in DOCS for m in pattern.finditer((REPO / doc).read_text())}
    assert {"bimacppo-graph", "bimacppo-train"} <= named, named
    assert named <= set(scripts), sorted(named - set(scripts))


def parameter_tables(text: str):
    """Rows (names, default cell) of every markdown table whose first header cell is ``parameter``."""
    tables, rows = [], None
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")] if line.lstrip().startswith("|") else None
        if cells is None:
            rows = None
            continue
        if rows is None:
            if cells[0].lower() == "parameter":
                rows = []
                tables.append(rows)
            else:
                rows = False
            continue
        if rows is False or set(cells[0]) <= set("-: "):
            continue
        rows.append((re.findall(r"`([^`]+)`", cells[0]), cells[1] if len(cells) > 1 else ""))
    return tables


def test_parameter_tables_list_the_nodes_parameters_with_their_yaml_defaults():
    C = composition()
    for doc in DOCS:
        tables = parameter_tables((REPO / doc).read_text())
        if not tables:
            continue
        assert doc in PARAMETER_TABLES, f"{doc} has a parameter table; name its node in PARAMETER_TABLES"
        e = C.entry(PARAMETER_TABLES[doc])
        declared = declared_parameters(e.node_class.split(":")[0])
        yaml_values = C.file_parameters(e, lambda pkg: str(REPO / pkg))
        listed = {}
        for rows in tables:
            for names, default in rows:
                listed.update({n: default for n in names})
        assert set(listed) == set(declared), (doc, sorted(set(listed) ^ set(declared)))
        assert set(yaml_values) <= set(declared), sorted(set(yaml_values) - set(declared))
        for name, cell in listed.items():
            literal = re.fullmatch(r"`([^`]*)`", cell)
            if literal and name in yaml_values:
                assert literal.group(1) == str(yaml_values[name]), (doc, name, cell, yaml_values[name])


def params_file_sections():
    """(params file, node section, node module, its values) of every ``config/*.params.yaml``: a
    section is a composition node, or a console script of that name (``mcap_player``)."""
    import yaml
    C, scripts = composition(), console_scripts()
    out = []
    for path in sorted(REPO.glob("bimacppo_*/config/*.params.yaml")):
        for section, body in (yaml.safe_load(path.read_text()) or {}).items():
            names = [e for e in C.NODES if e.name == section]
            module = names[0].node_class.split(":")[0] if names else scripts[section][1].split(":")[0]
            out.append((path.relative_to(REPO), section, module, C.flatten(body["ros__parameters"])))
    return out


def test_params_files_set_declared_parameters_to_their_declared_defaults():
    """A params file is the values a composition starts a node with; what it leaves out keeps the
    node's declared default. A key the node does not declare would be ignored by rclpy, and a
    value that differs from the declared default would make ``ros2 run`` without the file start
    another node than the launch file."""
    sections = params_file_sections()
    assert {s for _, s, _, _ in sections} >= {e.name for e in composition().NODES} | {"mcap_player"}
    for path, section, module, values in sections:
        declared = declared_parameters(module)
        assert set(values) <= set(declared), (str(path), section, sorted(set(values) - set(declared)))
        for name, value in values.items():
            if declared[name] is not None:
                assert value == declared[name], (str(path), section, name, value, declared[name])


# ----------------------------------------------------------------------------- the checker itself
def test_the_checker_catches_misspellings(checker):
    """Each kind of drift the test above guards against is reported (so its silence means something)."""
    def problems(line):
        out, cwd = [], REPO
        for _, tokens in commands([line], 1):
            found, cwd = checker.command(tokens, cwd)
            out += found
        return out
    assert problems("bimacppo-graph --episodes 5 --output run.mcap") == []
    assert problems(".venv/bin/bimacppo-sim render --map dual_lane_4way -o x.png") == []
    assert any("--episode" in p for p in problems("bimacppo-graph --episode 5"))
    assert any("--n-svs" in p for p in problems("bimacppo-sim render --n-svs 3"))
    assert any("--run-dir" in p for p in problems("bimacppo-sim render --run-dir x"))   # another CLI's flag
    assert any("no console script" in p for p in problems("bimacppo-evalute p.pt"))
    assert any("watchdog_timout_s" in p for p in problems("controller_node --ros-args -p watchdog_timout_s:=1"))
    assert problems("controller_node --ros-args -p watchdog_timeout_s:=1") == []
    assert any("is a node" in p for p in problems("planner_node --policy x.pt"))
    assert any("no such file" in p for p in problems("world_node --ros-args --params-file nowhere.yaml"))
    assert any("no executable of bimacppo_sim" in p for p in problems("ros2 run bimacppo_sim planner_node"))
    assert any("'episode'" in p for p in problems("ros2 launch bimacppo_bringup bimacppo.launch.py episode:=3"))
    assert problems("cd ros2_ws && ros2 run bimacppo_sim world_node --ros-args "
                    "--params-file src/bimacppo_sim/config/world.params.yaml") == []
    assert any("no such script" in p for p in problems("scripts/nowhere.sh"))
    assert any("--episodez" in p for p in problems("python scripts/bench_train.py --episodez 5"))
    assert "port" in declared_parameters("bimacppo_viz.ros.live_view")
    assert "planner_result_topic" in declared_parameters("bimacppo_viz.ros.live_view")   # a loop over a table
    assert declared_parameters("bimacppo_sim.ros.world_node")["resend_warn_after"] == 10   # through an alias


@pytest.mark.parametrize("module, usage", [("bimacppo_bag.recorder", "usage: mcap_recorder"),
                                           ("bimacppo_bag.player", "usage: mcap_player")])
def test_bag_tools_take_an_option_for_no_file_name(module, usage, tmp_path):
    """An option before ``--ros-args`` is no file name: ``mcap_recorder --verbose`` is a
    one-line usage error (exit 2) and writes nothing, ``--help`` prints the usage (exit 0) and
    writes nothing either (a file named ``--help`` would be the bug)."""
    import subprocess
    env = dict(os.environ, AMENT_PREFIX_PATH=os.environ.get("AMENT_PREFIX_PATH", sys.prefix))
    r = subprocess.run([sys.executable, "-m", module, "--verbose"], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=60)
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert r.returncode == 2 and len(errors) == 1 and usage in errors[0], r.stdout + r.stderr
    assert "Traceback" not in r.stderr and list(tmp_path.iterdir()) == []
    r = subprocess.run([sys.executable, "-m", module, "--help"], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.startswith("usage: ") and "--ros-args" in r.stdout, r.stdout + r.stderr
    assert "Traceback" not in r.stderr and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("module", ["bimacppo_sim.ros.world_node", "bimacppo_planner.ros.planner_node",
                                    "bimacppo_mpc.ros.controller_node", "bimacppo_curriculum.ros.curriculum_node",
                                    "bimacppo_viz.ros.live_view"])
def test_nodes_print_their_usage_for_help_and_do_not_start(module, tmp_path):
    """``world_node --help`` prints how ROS arguments are passed and the module's docstring, and
    exits 0 at once instead of starting the node."""
    import subprocess
    env = dict(os.environ, AMENT_PREFIX_PATH=os.environ.get("AMENT_PREFIX_PATH", sys.prefix))
    r = subprocess.run([sys.executable, "-m", module, "--help"], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.startswith("usage: ") and "--ros-args" in r.stdout and "docs/parameters.md" in r.stdout
    doc = importlib.import_module(module).__doc__.strip().splitlines()[0]
    assert doc in r.stdout
    assert "Traceback" not in r.stderr and list(tmp_path.iterdir()) == []


def test_parameters_page_is_the_nodes_declarations():
    """docs/parameters.md is what scripts/parameter_tables.py prints from the nodes' declare()
    calls: every node executable is on it, and it changes when a parameter does."""
    mod = load_script("parameter_tables")
    nodes = {exe for exe, (_, target) in console_scripts().items() if is_node_executable(target)}
    assert nodes == {exe for exe, _ in mod.NODES}, nodes ^ {exe for exe, _ in mod.NODES}
    for exe, module in mod.NODES:
        assert {r[0] for r in mod.declarations(module)} == set(declared_parameters(module)), exe
    expected = mod.page()
    assert (REPO / "docs" / "parameters.md").read_text() == expected, \
        "docs/parameters.md is stale: run .venv/bin/python scripts/parameter_tables.py > docs/parameters.md"
