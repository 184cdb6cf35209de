"""One configuration mechanism: packaged YAML defaults, overlays, strict frozen dataclasses.

The rules (docs/architecture.md, "Configuration"):

* **The packaged YAML is the only place a default is written.** A config class declares its
  keys, their types and ranges, but no values: ``@config_class(PACKAGED, "section")`` reads the
  defaults from the packaged file when the class is defined, so ``Cls()`` *is* the packaged
  configuration and ``Cls(key=value)`` changes one key. The packaged file must list every key
  and nothing else, and must itself be valid; otherwise the import fails naming the file.
* **A user's file or dict is an overlay.** It lists only what it changes and is deep-merged onto
  the packaged defaults: mappings (sections, dict-valued keys) merge key by key, every other
  value replaces. Dotted keys (``{"reward.step": -0.1}``) address nested keys. A saved dict that
  lists every key (a checkpoint) loads the same way, so a key added since it was saved takes the
  packaged default.
* **A record is read as what it meant.** A config saved with a run (:func:`from_record`) lists
  every key it had; a key added since that changes behaviour declares ``setting(absent=...)``,
  the value that reproduces what the code did before the key existed, so an old run's recorded
  controller is not misread as today's default. A key without ``absent`` takes the packaged
  default there as well.
* **Nothing is silently ignored.** An unknown key is refused with the closest known one
  suggested; a wrong type or an out-of-range value is refused. Every message names the file (or
  the dict) that set the key and the dotted key, e.g.
  ``run.yaml: unknown key 'train.num_env' (did you mean 'num_envs'?)``.
* **The result is a frozen dataclass**, validated in ``__post_init__``: ``dataclasses.replace``
  and direct construction are checked exactly like a file.

Errors are :class:`ConfigError`, a ``ValueError``. This module imports only the standard library
and PyYAML, so every package can use it.
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import math
import types
import typing
from importlib import resources
from pathlib import Path
from typing import Any, Mapping, Union

import yaml

__all__ = ["ConfigError", "Packaged", "config_class", "setting", "runtime", "invalid", "load", "from_dict",
           "from_record", "build", "read_yaml", "to_dict", "is_config_class"]

_META = "bimacppo_common.config"
_UNSET = object()     # a key that declares no ``absent`` value


class ConfigError(ValueError):
    """A configuration file, dict or value is invalid. ``source`` is the file (or dict) that set
    the offending value, ``key`` its dotted path within the configuration (``()`` when the
    problem is not one key's, e.g. an unreadable file)."""

    def __init__(self, detail: str, *, source: str | None = None, key: tuple[str, ...] | str = ()):
        if isinstance(key, str):
            key = tuple(key.split(".")) if key else ()
        self.detail, self.source, self.key = detail, source, tuple(key)
        head = f"{source}: " if source else ""
        where = f"key '{'.'.join(self.key)}' " if self.key else ""
        super().__init__(head + where + detail)

    def within(self, prefix: tuple[str, ...] = (), source: str | None = None) -> "ConfigError":
        """The same problem, seen from a section ``prefix`` up and attributed to ``source``."""
        return ConfigError(self.detail, source=source or self.source, key=(*prefix, *self.key))


def invalid(key: str, detail: str) -> ConfigError:
    """For a class's ``_check`` (cross-key rules): ``raise invalid("k1", "must be >= key 'k0'")``.
    ``key`` is relative to the class; the loader adds the section path and the file."""
    return ConfigError(detail, key=key)


# ----------------------------------------------------------------------------- declaring keys
@dataclasses.dataclass(frozen=True)
class _Rule:
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple | None = None
    length: int | None = None
    min_length: int | None = None
    keys: tuple | None = None
    absent: Any = _UNSET


def setting(*, lo: float | None = None, hi: float | None = None, lo_open: bool = False, hi_open: bool = False,
            choices=None, length: int | None = None, min_length: int | None = None, keys=None,
            absent: Any = _UNSET) -> Any:
    """Declare a key's allowed values (its type comes from the annotation, its default from the
    packaged YAML). ``lo``/``hi`` (``*_open``: exclusive) and ``choices`` apply to numbers and
    strings, also to each item of a list or dict value; ``length``/``min_length`` to lists;
    ``keys`` is the exact key set of a dict value. ``absent`` is the value a saved record
    without this key means (:func:`from_record`): what the code did before the key existed."""
    rule = _Rule(lo, hi, lo_open, hi_open, None if choices is None else tuple(choices), length, min_length,
                 None if keys is None else tuple(keys), absent)
    return dataclasses.field(metadata={_META: rule})


def runtime(default: Any) -> Any:
    """A field that is not configuration (e.g. where the config was read from): never read from
    or written to YAML, so its default is written in the class."""
    return dataclasses.field(default=default, metadata={_META: None})


class Packaged:
    """A YAML file shipped inside a package: the defaults of the config classes built on it."""

    def __init__(self, package: str, resource: str):
        self.package, self.resource = package, resource
        self._data: dict | None = None

    @property
    def path(self) -> str:
        return str(resources.files(self.package).joinpath(self.resource))

    def data(self) -> dict:
        if self._data is None:
            text = resources.files(self.package).joinpath(self.resource).read_text()
            self._data = _parse(text, self.path)
        return self._data

    def section(self, name: str | None) -> Mapping:
        data = self.data()
        if name is None:
            return data
        if not isinstance(data.get(name), Mapping):
            raise ConfigError("packaged defaults must be a mapping", source=self.path, key=name)
        return data[name]

    def __repr__(self) -> str:
        return f"Packaged({self.package!r}, {self.resource!r})"


@dataclasses.dataclass(frozen=True)
class _Field:
    type: Any
    rule: _Rule


@dataclasses.dataclass(frozen=True)
class _Spec:
    packaged: Packaged
    section: str | None
    fields: dict          # name -> _Field, in declaration order (config keys only)


def is_config_class(obj: Any) -> bool:
    return isinstance(obj, type) and "__config_spec__" in obj.__dict__


def config_class(packaged: Packaged, section: str | None = None):
    """Make a frozen dataclass whose defaults are ``packaged``'s mapping (or its ``section``).

    Annotated attributes are the keys; a key may be declared with :func:`setting` for its range,
    never with a value. A key whose type is another config class is a section (its defaults are
    that class's). Cross-key rules go in a method ``_check(self)`` that raises :func:`invalid`.
    """
    def wrap(cls):
        if "__post_init__" in cls.__dict__:
            raise TypeError(f"{cls.__name__}: put cross-key rules in _check(self), not __post_init__")
        where = ((section,) if section else ())
        raw = packaged.section(section)
        hints = typing.get_type_hints(cls)
        specs: dict[str, _Field] = {}
        for name in cls.__dict__.get("__annotations__", {}):
            typ = hints[name]
            if typing.get_origin(typ) is typing.ClassVar:
                continue
            current = cls.__dict__.get(name, dataclasses.MISSING)
            if current is not dataclasses.MISSING and not isinstance(current, dataclasses.Field):
                raise TypeError(f"{cls.__name__}.{name}: defaults are written in {packaged.path}, not in the class")
            meta = dict(current.metadata) if isinstance(current, dataclasses.Field) else {}
            if _META in meta and meta[_META] is None:      # runtime(): not configuration
                continue
            rule = meta.get(_META) or _Rule()
            meta[_META] = rule
            if is_config_class(_unoptional(typ)[0]):
                setattr(cls, name, dataclasses.field(default_factory=_unoptional(typ)[0], metadata=meta))
            else:
                if name not in raw:
                    raise ConfigError("missing from the packaged defaults (every key's default is written there)",
                                      source=packaged.path, key=(*where, name))
                try:
                    value = _coerce(typ, raw[name], rule, (name,))
                except ConfigError as exc:
                    raise exc.within(where, packaged.path) from None
                if isinstance(value, (dict, list)):
                    setattr(cls, name, dataclasses.field(default_factory=lambda v=value: copy.deepcopy(v),
                                                         metadata=meta))
                else:
                    setattr(cls, name, dataclasses.field(default=value, metadata=meta))
            specs[name] = _Field(typ, rule)
        extra = sorted(set(raw) - set(specs))
        if extra:
            raise ConfigError(f"unknown key '{'.'.join((*where, str(extra[0])))}' in the packaged defaults "
                              f"(keys of {cls.__name__}: {', '.join(specs)})", source=packaged.path)
        cls.__post_init__ = _post_init
        cls.__config_spec__ = _Spec(packaged, section, specs)
        cls = dataclasses.dataclass(frozen=True)(cls)
        try:
            cls()   # the packaged defaults must pass every rule, cross-key ones included
        except ConfigError as exc:
            raise exc.within(where, packaged.path) from None
        return cls
    return wrap


def _post_init(self) -> None:
    spec: _Spec = type(self).__config_spec__
    try:
        for name, f in spec.fields.items():
            value = getattr(self, name)
            coerced = _coerce(f.type, value, f.rule, (name,))
            if coerced is not value:
                object.__setattr__(self, name, coerced)
        check = getattr(self, "_check", None)
        if check is not None:
            check()
    except ConfigError as exc:
        raise (exc if exc.source else exc.within(source=type(self).__name__)) from None


# ----------------------------------------------------------------------------- checking values
def _unoptional(typ) -> tuple[Any, bool]:
    if typing.get_origin(typ) in (Union, types.UnionType):
        args = typing.get_args(typ)
        rest = [a for a in args if a is not type(None)]
        if len(rest) != 1:
            raise TypeError(f"unsupported config type {typ!r}: only X | None unions")
        return rest[0], len(rest) < len(args)
    return typ, False


def _range(value, rule: _Rule, key, what: str) -> None:
    if rule.choices is not None and value not in rule.choices:
        raise ConfigError(f"{what}must be one of {list(rule.choices)}, got {value!r}", key=key)
    lo_bad = rule.lo is not None and (value <= rule.lo if rule.lo_open else value < rule.lo)
    hi_bad = rule.hi is not None and (value >= rule.hi if rule.hi_open else value > rule.hi)
    if lo_bad or hi_bad:
        if rule.lo is not None and rule.hi is not None:
            want = f"in {'(' if rule.lo_open else '['}{rule.lo}, {rule.hi}{')' if rule.hi_open else ']'}"
        elif rule.lo is not None:
            want = f"{'>' if rule.lo_open else '>='} {rule.lo}"
        else:
            want = f"{'<' if rule.hi_open else '<='} {rule.hi}"
        raise ConfigError(f"{what}must be {want}, got {value!r}", key=key)


def _coerce(typ, value, rule: _Rule, key: tuple, item: str = ""):
    """``value`` as ``typ`` (YAML scalars that mean the type; no bool as a number), checked
    against ``rule``; raises ConfigError with ``key``. ``item`` names a list item in messages."""
    typ, optional = _unoptional(typ)
    if value is None and optional:
        return None
    what = f"{item} " if item else ""

    def fail(detail):
        raise ConfigError(what + detail, key=key)

    if is_config_class(typ):
        if not isinstance(value, typ):
            fail(f"must be a {typ.__name__} section, got {type(value).__name__}")
        return value
    if typ is bool:
        if not isinstance(value, bool):
            fail(f"must be true or false, got {value!r}")
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            fail(f"must be an integer, got {value!r}")
        _range(value, rule, key, what)
        return value
    if typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            fail(f"must be a number, got {value!r}")
        if not math.isfinite(value):
            fail(f"must be finite, got {value!r}")
        _range(value, rule, key, what)
        return value if type(value) is float else float(value)
    if typ is str:
        if not isinstance(value, str):
            fail(f"must be a string, got {value!r}")
        _range(value, rule, key, what)
        return value
    origin, args = typing.get_origin(typ), typing.get_args(typ)
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
        if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
            fail(f"must be a list, got {value!r}")
        if rule.length is not None and len(value) != rule.length:
            fail(f"must list {rule.length} values, got {list(value)!r}")
        if rule.min_length is not None and len(value) < rule.min_length:
            fail(f"must list at least {rule.min_length} value(s), got {list(value)!r}")
        out = tuple(_coerce(args[0], v, rule, key, item=f"{what}item {k}".strip()) for k, v in enumerate(value))
        return value if isinstance(value, tuple) and all(a is b for a, b in zip(out, value)) else out
    if origin is dict and len(args) == 2 and args[0] is str:
        if not isinstance(value, Mapping):
            fail(f"must be a mapping, got {value!r}")
        if rule.keys is not None and set(value) != set(rule.keys):
            fail(f"must map exactly {list(rule.keys)}, got {list(value)}")
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                fail(f"keys must be strings, got {k!r}")
            out[k] = _coerce(args[1], v, rule, (*key, k))
        return value if isinstance(value, dict) and all(out[k] is value[k] for k in out) else out
    raise TypeError(f"unsupported config type {typ!r} for key {'.'.join(key)!r}")   # a programming error


# ----------------------------------------------------------------------------- loading
def _parse(text: str, source: str) -> dict:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"not valid YAML ({' '.join(str(exc).split())})", source=source) from None
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"top level must be a mapping of keys to values, got {type(data).__name__}", source=source)
    return dict(data)


def read_yaml(path: str | Path) -> tuple[dict, str]:
    """A YAML file's top-level mapping and its name for messages."""
    source = str(path)
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read config file ({exc.strerror or exc})", source=source) from None
    return _parse(text, source), source


def _expand(data: Mapping, source: str, prefix: tuple) -> dict:
    """Dotted keys to nested mappings: {"reward.step": 1} -> {"reward": {"step": 1}}."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"must be a mapping, got {type(data).__name__}", source=source, key=prefix)
    out: dict = {}
    for k, v in data.items():
        if not isinstance(k, str):
            raise ConfigError(f"unknown key {k!r} (keys are strings)", source=source, key=prefix)
        head, *rest = k.split(".")
        if rest:
            v = {".".join(rest): v}
        if isinstance(v, Mapping):
            v = _expand(v, source, (*prefix, head))
            if isinstance(out.get(head), dict):
                v = _merged(out[head], v)
        out[head] = v
    return out


def _merged(base: dict, over: Mapping) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merged(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), dict) else v
    return out


def _unknown(key_path: tuple, known, source: str) -> ConfigError:
    name = str(key_path[-1])
    close = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    hint = f"did you mean '{close[0]}'?" if close else f"known: {', '.join(known)}"
    return ConfigError(f"unknown key '{'.'.join(map(str, key_path))}' ({hint})", source=source)


def _check_keys(cls, data: Mapping, prefix: tuple, source: str) -> None:
    spec: _Spec = cls.__config_spec__
    for k, v in data.items():
        if k not in spec.fields:
            raise _unknown((*prefix, k), spec.fields, source)
        typ = _unoptional(spec.fields[k].type)[0]
        if is_config_class(typ):
            if v is None:
                continue
            if not isinstance(v, Mapping):
                raise ConfigError(f"is a section and must be a mapping, got {type(v).__name__}", source=source,
                                  key=(*prefix, k))
            _check_keys(typ, v, (*prefix, k), source)
        elif spec.fields[k].rule.keys is not None and isinstance(v, Mapping):
            for kk in v:
                if kk not in spec.fields[k].rule.keys:
                    raise _unknown((*prefix, k, kk), spec.fields[k].rule.keys, source)


def _overlay(base: dict, data: Mapping, prefix: tuple, origin: dict, source: str) -> None:
    for k, v in data.items():
        path = (*prefix, k)
        if isinstance(base.get(k), dict):
            if v is None:            # an empty section lists nothing
                continue
            if isinstance(v, Mapping):
                _overlay(base[k], v, path, origin, source)
                continue
        base[k] = copy.deepcopy(v)
        origin[path] = source


def build(cls, *layers: tuple[Mapping, str]):
    """``cls``'s packaged defaults with each ``(mapping, source)`` layer deep-merged on, in order.

    Each layer's keys are checked before merging (so an unknown key names its own layer); the
    merged values are then checked, and a bad value is reported against the layer that set it.
    """
    merged = to_dict(cls())
    origin: dict[tuple, str] = {}
    names = []
    for data, source in layers:
        data = _expand(data, source, ())
        _check_keys(cls, data, (), source)
        _overlay(merged, data, (), origin, source)
        names.append(source)
    blame = " + ".join(names) or cls.__config_spec__.packaged.path
    return _construct(cls, merged, (), origin, blame)


def _construct(cls, data: dict, prefix: tuple, origin: dict, blame: str):
    spec: _Spec = cls.__config_spec__
    values = {}
    for name, f in spec.fields.items():
        typ = _unoptional(f.type)[0]
        values[name] = _construct(typ, data[name], (*prefix, name), origin, blame) if is_config_class(typ) \
            else data[name]
    try:
        return cls(**values)
    except ConfigError as exc:
        path = (*prefix, *exc.key)
        source = next((origin[path[:n]] for n in range(len(path), 0, -1) if path[:n] in origin), blame)
        raise exc.within(prefix, source) from None


def load(cls, path: str | Path | None = None, overrides: Mapping | None = None,
         overrides_source: str = "overrides"):
    """The packaged defaults, then the YAML file at ``path`` (if any), then ``overrides``."""
    layers = [read_yaml(path)] if path is not None else []
    if overrides:
        layers.append((overrides, overrides_source))
    return build(cls, *layers)


def from_dict(cls, data: Mapping, source: str = "<dict>"):
    """A dict in the YAML's layout (a saved config, or a few keys) overlaid on the defaults."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"expected a mapping of keys to values, got {type(data).__name__}", source=source)
    return build(cls, (data, source))


def _fill_absent(cls, data: Mapping) -> dict:
    """``data`` with every key it lacks that declares an ``absent`` value set to that value
    (sections too: a record made before a section existed lacks all of its keys)."""
    out = dict(data)
    for name, f in cls.__config_spec__.fields.items():
        typ = _unoptional(f.type)[0]
        if is_config_class(typ):
            sub = out.get(name, {})
            if isinstance(sub, Mapping):      # a recorded None (an optional section) stays None
                filled = _fill_absent(typ, sub)
                if filled or name in out:
                    out[name] = filled
        elif name not in out and f.rule.absent is not _UNSET:
            out[name] = copy.deepcopy(f.rule.absent)
    return out


def from_record(cls, data: Mapping, source: str = "<record>"):
    """A config saved with a run (every key it had then), read as what it meant: a key it lacks
    takes its declared ``absent`` value (the behaviour before that key existed), else the
    packaged default; an unknown key or a bad value is a ConfigError like any file's."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"expected a mapping of keys to values, got {type(data).__name__}", source=source)
    data = _expand(data, source, ())
    _check_keys(cls, data, (), source)
    return build(cls, (_fill_absent(cls, data), source))


def to_dict(obj) -> dict:
    """Plain YAML/JSON types (lists, not tuples; sections as dicts); ``from_dict`` reads it back."""
    def plain(v):
        if is_config_class(type(v)):
            return to_dict(v)
        if isinstance(v, (tuple, list)):
            return [plain(x) for x in v]
        if isinstance(v, Mapping):
            return {k: plain(x) for k, x in v.items()}
        return v
    return {name: plain(getattr(obj, name)) for name in type(obj).__config_spec__.fields}
