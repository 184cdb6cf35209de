"""Typed, validated configuration for the world, loaded from the package's YAML files.

Every tunable number of the simulator lives in ``bimacppo_sim/config/*.yaml``; the
dataclasses below only describe shape and admissible ranges so that a typo or an
out-of-range value fails loudly (naming file and key) instead of silently changing
the experiment.
"""
from __future__ import annotations

import dataclasses
import math
import pathlib
import typing
from dataclasses import dataclass, field

import yaml

CONFIG_DIR = pathlib.Path(__file__).resolve().parent / "config"
STYLES = ("aggressive", "moderate", "conservative")


def _rng(lo=None, hi=None, **kw):
    return field(metadata={"min": lo, "max": hi, **kw})


@dataclass(frozen=True)
class VehicleConfig:
    """EV geometry and physical input limits (Tesla Model 3, paper §II-B)."""
    wheelbase: float = _rng(0.5, 10.0)
    length: float = _rng(0.5, 20.0)
    width: float = _rng(0.3, 5.0)
    a_min: float = _rng(-20.0, 0.0)
    a_max: float = _rng(0.0, 20.0)
    delta_max: float = _rng(0.0, 1.5)
    v_min: float = _rng(0.0, 50.0)
    v_max: float = _rng(0.0, 50.0)


@dataclass(frozen=True)
class StyleConfig:
    """One hidden SV driving style: IDM parameters plus gap acceptance."""
    probability: float = _rng(0.0, 1.0)
    v_desired: float = _rng(0.5, 30.0)
    a_max: float = _rng(0.1, 10.0)
    b_comfortable: float = _rng(0.1, 10.0)
    b_max: float = _rng(0.1, 15.0)
    time_headway: float = _rng(0.0, 5.0)
    min_gap: float = _rng(0.0, 10.0)
    sv_gap: float = _rng(0.0, 10.0)
    yield_to_ev: bool = field(metadata={})
    ev_gap: float = _rng(-5.0, 10.0)
    brake_for_crossing_ev: bool = field(metadata={})
    respects_fcfs: bool = field(metadata={})


@dataclass(frozen=True)
class SVConfig:
    """Surrounding-vehicle model and spawn distribution."""
    styles: typing.Dict[str, StyleConfig] = field(metadata={"keys": STYLES})
    idm_delta: float = _rng(1.0, 10.0)
    lateral_accel_max: float = _rng(0.5, 15.0)
    path_sample: float = _rng(0.05, 2.0)
    grid_cell: float = _rng(0.1, 2.0)
    grid_radius: float = _rng(0.2, 3.0)
    lookahead: float = _rng(5.0, 200.0)
    conflict_margin: float = _rng(0.0, 10.0)
    conflict_cap_after_exit: float = _rng(0.0, 30.0)
    stop_margin: float = _rng(0.0, 10.0)
    commit_margin: float = _rng(0.0, 20.0)
    creep_speed: float = _rng(0.0, 10.0)
    request_distance: float = _rng(1.0, 200.0)
    ev_prediction_horizon: float = _rng(0.0, 10.0)
    ev_prediction_step: float = _rng(0.05, 5.0)
    min_speed_for_eta: float = _rng(0.01, 5.0)
    spawn_time_jitter: float = _rng(0.0, 20.0)
    spawn_speed_factor_min: float = _rng(0.0, 1.5)
    spawn_speed_factor_max: float = _rng(0.0, 1.5)
    min_spawn_distance: float = _rng(0.0, 100.0)
    slow_speed_factor_min: float = _rng(0.01, 1.0)
    slow_speed_factor_max: float = _rng(0.01, 1.0)


@dataclass(frozen=True)
class WorldConfig:
    """Episode-level settings; ``vehicle`` and ``sv`` come from their own files."""
    dt: float = _rng(1e-3, 1.0)
    time_limit: float = _rng(0.1, 3600.0)
    waypoint_spacing: float = _rng(0.5, 20.0)
    route_tail: float = _rng(0.0, 100.0)
    success_distance: float = _rng(0.0, 100.0)
    goal_any_lane: bool = field(metadata={})
    offroad_check: str = field(metadata={"choices": ("corners", "centre", "off")})
    ev_start_distance_min: float = _rng(0.0, 500.0)
    ev_start_distance_max: float = _rng(0.0, 500.0)
    ev_speed_min: float = _rng(0.0, 30.0)
    ev_speed_max: float = _rng(0.0, 30.0)
    ev_nominal_speed: float = _rng(0.1, 30.0)
    graph_step: float = _rng(0.5, 20.0)
    lane_change_length: float = _rng(1.0, 100.0)
    lane_change_penalty: float = _rng(0.0, 1000.0)
    no_lane_change_zone: float = _rng(0.0, 100.0)
    vehicle: VehicleConfig = None
    sv: SVConfig = None

    @staticmethod
    def load(world: str | pathlib.Path | None = None, vehicle: str | pathlib.Path | None = None,
             sv: str | pathlib.Path | None = None) -> "WorldConfig":
        """Read world.yaml, vehicle.yaml and sv.yaml (package defaults unless paths are given)."""
        veh = load_dataclass(VehicleConfig, vehicle or CONFIG_DIR / "vehicle.yaml")
        svc = load_dataclass(SVConfig, sv or CONFIG_DIR / "sv.yaml")
        cfg = load_dataclass(WorldConfig, world or CONFIG_DIR / "world.yaml",
                             extra={"vehicle": veh, "sv": svc})
        return cfg


@dataclass(frozen=True)
class DriverConfig:
    """Scripted reference EV drivers (go / yield)."""
    target_speed: float = _rng(0.1, 30.0)
    lookahead_min: float = _rng(0.5, 50.0)
    lookahead_time: float = _rng(0.0, 10.0)
    speed_gain: float = _rng(0.0, 20.0)
    stop_margin: float = _rng(0.0, 20.0)
    stop_decel: float = _rng(0.1, 10.0)
    safe_time_gap: float = _rng(0.0, 30.0)
    watch_distance: float = _rng(0.0, 500.0)

    @staticmethod
    def load(path: str | pathlib.Path | None = None) -> "DriverConfig":
        return load_dataclass(DriverConfig, path or CONFIG_DIR / "drivers.yaml")


def _check_value(cls_name, f, value, where):
    meta = f.metadata
    tp = f.type if not isinstance(f.type, str) else eval(f.type, globals(), typing.__dict__)  # noqa: S307
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{where}: key '{f.name}' must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise ValueError(f"{where}: key '{f.name}' must be finite, got {value!r}")
    elif tp is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{where}: key '{f.name}' must be true/false, got {value!r}")
    elif tp is str:
        if not isinstance(value, str):
            raise ValueError(f"{where}: key '{f.name}' must be a string, got {value!r}")
        if "choices" in meta and value not in meta["choices"]:
            raise ValueError(f"{where}: key '{f.name}' must be one of {meta['choices']}, got {value!r}")
    if tp is float:
        lo, hi = meta.get("min"), meta.get("max")
        if lo is not None and value < lo or hi is not None and value > hi:
            raise ValueError(f"{where}: key '{f.name}' = {value} out of range [{lo}, {hi}]")
    return value


def load_dataclass(cls, source, extra=None):
    """Build frozen dataclass ``cls`` from a YAML file path or a dict, validating every key."""
    if isinstance(source, dict):
        data, where = dict(source), f"<{cls.__name__} dict>"
    else:
        where = str(source)
        try:
            with open(source) as fh:
                data = yaml.safe_load(fh)
        except FileNotFoundError:
            raise ValueError(f"config file not found: {source}") from None
        except yaml.YAMLError as exc:
            raise ValueError(f"{where}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a mapping of keys, got {type(data).__name__}")
    return _build(cls, data, where, extra or {})


def _build(cls, data, where, extra):
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(fields)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {sorted(unknown)} for {cls.__name__}")
    kwargs = {}
    for name, f in fields.items():
        if name in extra:
            kwargs[name] = extra[name]
            continue
        if name not in data:
            raise ValueError(f"{where}: missing key '{name}' for {cls.__name__}")
        value = data[name]
        if name == "styles":
            if not isinstance(value, dict) or set(value) != set(STYLES):
                raise ValueError(f"{where}: key 'styles' must define exactly {STYLES}")
            kwargs[name] = {k: _build(StyleConfig, value[k] or {}, f"{where} [styles.{k}]", {})
                            for k in STYLES}
        else:
            kwargs[name] = _check_value(cls.__name__, f, value, where)
    obj = cls(**kwargs)
    _cross_check(obj, where)
    return obj


def _cross_check(obj, where):
    def bad(msg):
        raise ValueError(f"{where}: {msg}")
    if isinstance(obj, VehicleConfig):
        if obj.v_min > obj.v_max:
            bad("v_min must be <= v_max")
    elif isinstance(obj, SVConfig):
        total = sum(s.probability for s in obj.styles.values())
        if abs(total - 1.0) > 1e-6:
            bad(f"style probabilities must sum to 1, got {total}")
        if obj.spawn_speed_factor_min > obj.spawn_speed_factor_max:
            bad("spawn_speed_factor_min must be <= spawn_speed_factor_max")
        if obj.slow_speed_factor_min > obj.slow_speed_factor_max:
            bad("slow_speed_factor_min must be <= slow_speed_factor_max")
    elif isinstance(obj, WorldConfig):
        if obj.ev_start_distance_min > obj.ev_start_distance_max:
            bad("ev_start_distance_min must be <= ev_start_distance_max")
        if obj.ev_speed_min > obj.ev_speed_max:
            bad("ev_speed_min must be <= ev_speed_max")
