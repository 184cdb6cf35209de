"""MCAP with the ``ros2`` profile, written the way rosbag2 writes it, read back defensively.

Schemas: ``ros2msg`` encoding, the root .msg text followed by every dependency, each
behind an 80-'=' line and ``MSG: pkg/Type`` (rosbag2's LocalMessageDefinitionSource:
dependencies found by the same field-type pattern, visited depth-first in sorted order,
each once). Channels: ``cdr`` messages with ``offered_qos_profiles`` metadata in the
rosbag2 >= Jazzy YAML form (policy names as strings), so ``ros2 bag play`` re-offers the
recorded QoS (a latched /goal_pose stays latched) and Foxglove decodes everything.

No rclpy import here: the file is pure (besides message definitions on disk), so the
reader side works in any Python environment with ``mcap``.
"""
from __future__ import annotations

import io
import os
import pathlib
import re
import sys
from dataclasses import dataclass, field
from typing import Callable, Dict, Iterator, List, Optional, Tuple

import yaml

SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
PROFILE = "ros2"
DELIMITER = "=" * 80 + "\n"

_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_PRIMITIVES = frozenset({"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16",
                         "uint16", "int32", "uint32", "int64", "uint64", "string"})
_NAME = r"[a-zA-Z][a-zA-Z0-9_]*"
_TYPE_RE = re.compile(rf"^({_NAME})/(?:({_NAME})/)?({_NAME})$")


class DefinitionNotFound(LookupError):
    """A .msg file needed for a schema is not installed (names the type and where it looked)."""


def _share_dirs(package: str) -> List[pathlib.Path]:
    """Where ``package``'s share/ may live: the ament index first, then this interpreter's prefix."""
    dirs = []
    for prefix in filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)):
        dirs.append(pathlib.Path(prefix) / "share" / package)
    dirs.append(pathlib.Path(sys.prefix) / "share" / package)
    return dirs


def split_type(type_name: str) -> Tuple[str, str, str]:
    """``pkg/msg/Type`` or ``pkg/Type`` -> (pkg, 'msg', Type)."""
    m = _TYPE_RE.match(type_name)
    if not m:
        raise DefinitionNotFound(f"not a ROS message type name: {type_name!r}")
    return m.group(1), m.group(2) or "msg", m.group(3)


def _load_msg(type_name: str, cache: Dict[str, str]) -> str:
    if type_name in cache:
        return cache[type_name]
    pkg, ns, name = split_type(type_name)
    tried = []
    for d in _share_dirs(pkg):
        path = d / ns / f"{name}.msg"
        tried.append(str(path))
        if path.is_file():
            cache[type_name] = path.read_text()
            return cache[type_name]
    raise DefinitionNotFound(f"no .msg definition for {type_name}; looked in {tried} "
                             "(set AMENT_PREFIX_PATH to the prefix holding share/<pkg>/msg)")


def _dependencies(text: str, package: str) -> List[str]:
    deps = set()
    for m in _FIELD_TYPE.finditer(text):
        t = m.group(1)
        if t in _PRIMITIVES:
            continue
        deps.add(t if "/" in t else f"{package}/{t}")
    return sorted(deps)


def full_definition(type_name: str, _cache: Optional[Dict[str, str]] = None) -> str:
    """The complete ``ros2msg`` text for ``type_name`` exactly as rosbag2 concatenates it."""
    cache = {} if _cache is None else _cache
    seen = set()

    def rec(t: str, depth: int) -> str:
        if depth <= 0:
            raise DefinitionNotFound(f"definition of {type_name} nests too deep")
        text = _load_msg(t, cache)
        out = text
        for dep in _dependencies(text, split_type(t)[0]):
            if dep not in seen:
                seen.add(dep)
                out += "\n" + DELIMITER + f"MSG: {dep}\n" + rec(dep, depth - 1)
        return out

    return rec(type_name, 50)


# ----------------------------------------------------------------------------- QoS metadata
_INFINITE = {"sec": 9223372036, "nsec": 854775807}


@dataclass(frozen=True)
class QosRecord:
    """The policies rosbag2 stores per offering publisher (durations in ns; None = infinite)."""
    history: str = "keep_last"
    depth: int = 10
    reliability: str = "reliable"
    durability: str = "volatile"
    deadline_ns: Optional[int] = None
    lifespan_ns: Optional[int] = None
    liveliness: str = "automatic"
    liveliness_lease_ns: Optional[int] = None
    avoid_ros_namespace_conventions: bool = False


def _dur(ns: Optional[int]) -> dict:
    if ns is None or ns <= 0 or ns >= _INFINITE["sec"] * 10**9:
        return dict(_INFINITE)
    return {"sec": int(ns // 10**9), "nsec": int(ns % 10**9)}


def _undur(d) -> Optional[int]:
    if not isinstance(d, dict):
        return None
    sec, nsec = int(d.get("sec", 0)), int(d.get("nsec", 0))
    if sec >= 2147483647 or (sec, nsec) == (_INFINITE["sec"], _INFINITE["nsec"]) or (sec == 0 and nsec == 0):
        return None
    return sec * 10**9 + nsec


def qos_to_yaml(records: List[QosRecord]) -> str:
    """rosbag2's ``offered_qos_profiles`` string (a YAML sequence, one entry per publisher)."""
    items = [{
        "history": r.history, "depth": int(r.depth), "reliability": r.reliability,
        "durability": r.durability, "deadline": _dur(r.deadline_ns), "lifespan": _dur(r.lifespan_ns),
        "liveliness": r.liveliness, "liveliness_lease_duration": _dur(r.liveliness_lease_ns),
        "avoid_ros_namespace_conventions": bool(r.avoid_ros_namespace_conventions),
    } for r in records]
    return yaml.safe_dump(items, default_flow_style=False, sort_keys=False) if items else ""


_LEGACY = {  # rosbag2 < 9 wrote the rmw enum values as integers
    "history": {0: "system_default", 1: "keep_last", 2: "keep_all"},
    "reliability": {0: "system_default", 1: "reliable", 2: "best_effort"},
    "durability": {0: "system_default", 1: "transient_local", 2: "volatile"},
    "liveliness": {0: "system_default", 1: "automatic", 3: "manual_by_topic"},
}


def qos_from_yaml(text: str) -> List[QosRecord]:
    """Parse ``offered_qos_profiles`` (string or integer policies); bad text -> []."""
    if not text:
        return []
    try:
        items = yaml.safe_load(text)
    except yaml.YAMLError:
        return []
    if not isinstance(items, list):
        return []
    out = []
    for it in items:
        if not isinstance(it, dict):
            continue
        pol = {}
        for k, legacy in _LEGACY.items():
            v = it.get(k, QosRecord.__dataclass_fields__[k].default)
            pol[k] = legacy.get(v, "system_default") if isinstance(v, int) else str(v)
        out.append(QosRecord(history=pol["history"], depth=int(it.get("depth", 10) or 0),
                             reliability=pol["reliability"], durability=pol["durability"],
                             deadline_ns=_undur(it.get("deadline")), lifespan_ns=_undur(it.get("lifespan")),
                             liveliness=pol["liveliness"],
                             liveliness_lease_ns=_undur(it.get("liveliness_lease_duration")),
                             avoid_ros_namespace_conventions=bool(it.get("avoid_ros_namespace_conventions", False))))
    return out


# ----------------------------------------------------------------------------- reading
@dataclass
class ReadReport:
    """What a defensive read found: message count and, if it stopped early, why."""
    messages: int = 0
    complete: bool = True
    error: str = ""
    topics: Dict[str, int] = field(default_factory=dict)


def iter_mcap(path, report: Optional[ReadReport] = None, topics=None) -> Iterator[tuple]:
    """Yield (schema, channel, message) in file order from a possibly truncated/corrupt MCAP.

    A complete file is read through its summary; a file without a valid footer (recorder
    killed) or with a damaged index is scanned record by record, yielding everything up to
    the first unreadable byte. ``report`` (if given) says how far it got and why it stopped.
    """
    from mcap.reader import NonSeekingReader, SeekingReader

    report = report if report is not None else ReadReport()
    wanted = set(topics) if topics else None
    path = os.fspath(path)
    try:
        f = open(path, "rb")
    except OSError as exc:
        report.complete, report.error = False, f"cannot open {path}: {exc}"
        return
    with f:
        use_summary = False
        try:
            reader = SeekingReader(f)
            summary = reader.get_summary()
            use_summary = summary is not None and len(summary.chunk_indexes) > 0
        except Exception as exc:  # no footer / garbage at the end: fall back to scanning
            report.complete, report.error = False, f"no valid summary ({type(exc).__name__}: {exc})"
        if use_summary:
            try:
                for sch, ch, msg in reader.iter_messages(log_time_order=False):
                    if wanted is None or ch.topic in wanted:
                        report.messages += 1
                        report.topics[ch.topic] = report.topics.get(ch.topic, 0) + 1
                        yield sch, ch, msg
                return
            except Exception as exc:
                # indexed read failed part-way: rescan linearly, skipping what was yielded
                report.complete = False
                report.error = f"indexed read failed ({type(exc).__name__}: {exc})"
                skip = report.messages
                report.messages, report.topics = 0, {}
        else:
            skip = 0
        f.seek(0, io.SEEK_SET)
        try:
            n = 0
            for sch, ch, msg in NonSeekingReader(f).iter_messages(log_time_order=False):
                if wanted is not None and ch.topic not in wanted:
                    continue
                n += 1
                report.messages += 1
                report.topics[ch.topic] = report.topics.get(ch.topic, 0) + 1
                if n > skip:
                    yield sch, ch, msg
        except Exception as exc:
            report.complete = False
            report.error = (report.error + "; " if report.error else "") + \
                f"stopped after {report.messages} messages ({type(exc).__name__}: {exc})"


def open_writer(path, chunk_size: int, compression: str = "zstd", library: str = "bimacppo-recorder"):
    """An MCAP writer (ros2 profile) on a NEW file; returns (writer, file).

    An existing path is refused, never truncated: a recorder restarted after a crash with the same
    output name must not destroy the crash's readable recording. ValueError names the path."""
    from mcap.writer import CompressionType, Writer

    comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
    if compression not in comp:
        raise ValueError(f"compression must be one of {sorted(comp)}, got {compression!r}")
    try:
        f = open(path, "xb")
    except FileExistsError:
        kind = "a directory" if os.path.isdir(path) else "an existing file"
        raise ValueError(f"{path} is {kind}: refusing to overwrite it; name a new output file") from None
    except OSError as exc:
        raise ValueError(f"cannot create {path}: {exc.strerror}") from None
    w = Writer(f, chunk_size=int(chunk_size), compression=comp[compression])
    w.start(profile=PROFILE, library=library)
    return w, f


SchemaLookup = Callable[[str], str]
