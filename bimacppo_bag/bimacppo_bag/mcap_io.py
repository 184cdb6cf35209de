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

RUN_METADATA = "bimacppo"
"""Name of the metadata record in which the recorder states what the recorded graph ran on."""
MAP_ID_KEY = "map_id"         # the world's map_id parameter: a map id or a YAML path
MAP_YAML_KEY = "map_yaml"     # the text of that YAML file (only when map_id is a file)

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
    """What a defensive read found: message count and, if it stopped early or skipped, why.

    ``lost`` counts, per topic, the messages of damaged chunks that were skipped (known from
    the chunks' message indexes; a chunk without a readable index adds to ``lost_unknown``).
    ``metadata``: the file's metadata records, name -> key/values (a later record of a name
    updates an earlier one, the way rosbag2 takes its last ``rosbag2`` record).
    """
    messages: int = 0
    complete: bool = True
    error: str = ""
    topics: Dict[str, int] = field(default_factory=dict)
    chunks_skipped: int = 0
    lost: Dict[str, int] = field(default_factory=dict)
    lost_unknown: int = 0
    metadata: Dict[str, Dict[str, str]] = field(default_factory=dict)

    def fail(self, reason: str) -> None:
        self.complete = False
        self.error = f"{self.error}; {reason}" if self.error else reason

    def count(self, topic: str) -> None:
        self.messages += 1
        self.topics[topic] = self.topics.get(topic, 0) + 1

    def add_metadata(self, rec) -> None:
        self.metadata.setdefault(rec.name, {}).update(rec.metadata)


def _chunk_records(chunk) -> list:
    """Every record of a chunk, CRC-checked (a chunk written without CRC cannot be checked)."""
    from mcap.stream_reader import breakup_chunk
    return breakup_chunk(chunk, validate_crc=True)


def _index_counts(buf: bytes, channels: Dict[int, object]) -> Optional[Dict[str, int]]:
    """Messages per topic listed by the MessageIndex records in ``buf`` (None if unreadable)."""
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import MessageIndex
    counts: Dict[str, int] = {}
    pos = 0
    try:
        while pos + 9 <= len(buf):
            opcode, length = buf[pos], int.from_bytes(buf[pos + 1:pos + 9], "little")
            body = buf[pos + 9:pos + 9 + length]
            if len(body) != length:
                return None
            if opcode == Opcode.MESSAGE_INDEX:
                mi = MessageIndex.read(ReadDataStream(io.BytesIO(body)))
                ch = channels.get(mi.channel_id)
                topic = ch.topic if ch is not None else f"<channel {mi.channel_id}>"
                counts[topic] = counts.get(topic, 0) + len(mi.records)
            pos += 9 + length
    except Exception:
        return None
    return counts


def _lose(report: ReadReport, counts: Optional[Dict[str, int]], wanted) -> None:
    if counts is None:
        report.lost_unknown += 1
        return
    for topic, n in counts.items():
        if wanted is None or topic in wanted:
            report.lost[topic] = report.lost.get(topic, 0) + n


def _read_indexed_metadata(f, summary, report: ReadReport) -> None:
    """The metadata records a summary indexes, in file order; an unreadable one is reported."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Metadata

    for mi in sorted(summary.metadata_indexes, key=lambda m: m.offset):
        try:
            f.seek(mi.offset)
            buf = f.read(mi.length)
            if len(buf) != mi.length:
                raise EOFError(f"{len(buf)} of {mi.length} bytes")
            report.add_metadata(Metadata.read(ReadDataStream(io.BytesIO(buf[9:]))))
        except Exception as exc:
            report.fail(f"metadata {mi.name!r} at byte {mi.offset} unreadable ({type(exc).__name__}: {exc})")


def _iter_indexed(f, summary, report: ReadReport, wanted) -> Iterator[tuple]:
    """Messages of an indexed file in log-time order (ties: file order); damaged chunks skipped.

    Chunks are decoded lazily, when the earliest message they may hold is due, so memory
    stays at the chunks that overlap in time (the way the mcap SeekingReader merges them).
    """
    import heapq
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk, Message

    heap = [(ci.message_start_time, 0, ci.chunk_start_offset, 0, ci) for ci in summary.chunk_indexes]
    heapq.heapify(heap)
    while heap:
        t, kind, offset, idx, item = heapq.heappop(heap)
        if kind == 1:
            yield item
            continue
        ci = item
        try:
            f.seek(ci.chunk_start_offset)
            buf = f.read(ci.chunk_length)
            if len(buf) != ci.chunk_length:
                raise EOFError(f"{len(buf)} of {ci.chunk_length} bytes")
            records = _chunk_records(Chunk.read(ReadDataStream(io.BytesIO(buf[9:]))))
        except Exception as exc:
            report.chunks_skipped += 1
            report.fail(f"chunk at byte {ci.chunk_start_offset} skipped ({type(exc).__name__}: {exc})")
            f.seek(ci.chunk_start_offset + ci.chunk_length)
            _lose(report, _index_counts(f.read(ci.message_index_length), summary.channels), wanted)
            continue
        for i, rec in enumerate(records):
            if not isinstance(rec, Message):
                continue
            ch = summary.channels.get(rec.channel_id)
            if ch is None or (wanted is not None and ch.topic not in wanted):
                continue
            sch = summary.schemas.get(ch.schema_id) if ch.schema_id else None
            heapq.heappush(heap, (rec.log_time, 1, ci.chunk_start_offset, i, (sch, ch, rec)))


def _iter_linear(f, report: ReadReport, wanted) -> Iterator[tuple]:
    """Messages in file order, record by record, up to the first unreadable record.

    A chunk that fails its CRC (or does not decompress) is skipped and the scan goes on
    after it: its length field still tells where the next record starts.
    """
    from mcap.records import Channel, Chunk, Message, MessageIndex, Metadata, Schema
    from mcap.stream_reader import StreamReader

    schemas: Dict[int, object] = {}
    channels: Dict[int, object] = {}
    lost: Optional[Dict[str, int]] = None   # the message indexes after a skipped chunk

    def message(rec):
        ch = channels.get(rec.channel_id)
        if ch is None:
            report.lost_unknown += 1
            return None
        if wanted is not None and ch.topic not in wanted:
            return None
        return schemas.get(ch.schema_id) if ch.schema_id else None, ch, rec

    def take(rec):
        """A schema or channel is remembered, a message returned as (schema, channel, message)."""
        if isinstance(rec, Schema):
            schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            channels[rec.id] = rec
        elif isinstance(rec, Message):
            return message(rec)
        elif isinstance(rec, Metadata):
            report.add_metadata(rec)
        return None

    try:
        for rec in StreamReader(f, emit_chunks=True).records:
            if isinstance(rec, MessageIndex):
                if lost is not None:
                    ch = channels.get(rec.channel_id)
                    topic = ch.topic if ch is not None else f"<channel {rec.channel_id}>"
                    lost[topic] = lost.get(topic, 0) + len(rec.records)
                continue
            if lost is not None:
                _lose(report, lost if lost else None, wanted)
                lost = None
            if isinstance(rec, Chunk):
                try:
                    inner = _chunk_records(rec)
                except Exception as exc:
                    report.chunks_skipped += 1
                    report.fail(f"a chunk skipped ({type(exc).__name__}: {exc})")
                    lost = {}
                    continue
            else:
                inner = (rec,)
            for r in inner:
                item = take(r)
                if item is not None:
                    yield item
    except Exception as exc:
        report.fail(f"stopped after {report.messages} messages ({type(exc).__name__}: {exc})")
    if lost is not None:
        _lose(report, lost if lost else None, wanted)


def iter_mcap(path, report: Optional[ReadReport] = None, topics=None) -> Iterator[tuple]:
    """Yield (schema, channel, message) from a possibly damaged MCAP.

    A file with a valid summary is read through its chunk indexes in log-time order (a
    writer may store messages grouped by topic; playback needs time order). A file without
    a valid footer (recorder killed) or without chunk indexes is scanned record by record
    in file order, up to the first unreadable byte. Chunk CRCs are checked: a damaged chunk
    is skipped (its messages counted in ``report.lost``) and reading goes on after it.
    ``report`` (if given) says how far it got and what it skipped, and holds the file's
    metadata records once the iteration is done.
    """
    from mcap.reader import SeekingReader

    report = report if report is not None else ReadReport()
    wanted = set(topics) if topics else None
    path = os.fspath(path)
    try:
        f = open(path, "rb")
    except OSError as exc:
        report.fail(f"cannot open {path}: {exc}")
        return
    with f:
        summary = None
        try:
            summary = SeekingReader(f, validate_crcs=True).get_summary()
        except Exception as exc:  # no footer / garbage at the end: fall back to scanning
            report.fail(f"no valid summary ({type(exc).__name__}: {exc})")
        if summary is not None and summary.chunk_indexes:
            _read_indexed_metadata(f, summary, report)
            items = _iter_indexed(f, summary, report, wanted)
        else:
            f.seek(0, io.SEEK_SET)
            items = _iter_linear(f, report, wanted)
        for sch, ch, msg in items:
            report.count(ch.topic)
            yield sch, ch, msg


# ----------------------------------------------------------------------------- rosbag2 directories
class BagError(ValueError):
    """A bag path that cannot be played (names the path and the reason)."""


def bag_files(path) -> Tuple[List[str], Dict[str, str]]:
    """The MCAP files of a bag, in play order, and the QoS its metadata.yaml records per topic.

    ``path`` is an ``.mcap`` file (itself, no QoS) or a rosbag2 directory: its
    ``metadata.yaml`` lists the files (``relative_file_paths``, the order rosbag2 wrote them
    when it split the bag). Only the ``mcap`` storage is readable here; sqlite3 bags and
    file-compressed bags are refused with a BagError naming the reason.
    """
    path = os.fspath(path)
    if os.path.isfile(path):
        return [path], {}
    if not os.path.isdir(path):
        raise FileNotFoundError(f"no such file: {path}")
    meta_path = os.path.join(path, "metadata.yaml")
    if not os.path.isfile(meta_path):
        files = sorted(n for n in os.listdir(path) if n.endswith(".mcap"))
        if not files:
            raise BagError(f"{path} is a directory without metadata.yaml or .mcap files")
        return [os.path.join(path, n) for n in files], {}
    try:
        with open(meta_path) as fh:
            info = (yaml.safe_load(fh) or {})["rosbag2_bagfile_information"]
    except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
        raise BagError(f"{meta_path} is no rosbag2 metadata ({type(exc).__name__}: {exc})") from None
    storage = str(info.get("storage_identifier", "mcap"))
    if storage != "mcap":
        raise BagError(f"{path}: storage {storage!r} is not readable here (only 'mcap')")
    if str(info.get("compression_mode", "") or "").lower() == "file":
        raise BagError(f"{path}: file-compressed bags ({info.get('compression_format')}) are not readable here")
    names = info.get("relative_file_paths") or [f.get("path") for f in info.get("files") or []]
    files = [os.path.join(path, os.path.basename(str(n))) for n in names if n]
    missing = [f for f in files if not os.path.isfile(f)]
    if not files or missing:
        raise BagError(f"{path}: files listed in metadata.yaml are missing: {missing or 'none listed'}")
    qos = {}
    for t in info.get("topics_with_message_count") or []:
        tm = (t or {}).get("topic_metadata") or {}
        prof = tm.get("offered_qos_profiles")
        if tm.get("name") and prof:
            qos[str(tm["name"])] = prof if isinstance(prof, str) else yaml.safe_dump(prof)
    return files, qos


COMPRESSIONS = ("zstd", "lz4", "none")
"""Chunk compressions the writer offers (every MCAP reader decodes all three)."""


def open_writer(path, chunk_size: int, compression: str = "zstd", library: str = "bimacppo-recorder"):
    """An MCAP writer (ros2 profile) on a NEW file; returns (writer, file).

    An existing path is refused, never truncated: a recorder restarted after a crash with the same
    output name must not destroy the crash's readable recording. ValueError names the path."""
    from mcap.writer import CompressionType, Writer

    comp = dict(zip(COMPRESSIONS, (CompressionType.ZSTD, CompressionType.LZ4, CompressionType.NONE)))
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
