"""Typed, validated configuration of the world, over the package's YAML files.

Every tunable number of the simulator lives in ``bimacppo_sim/config/*.yaml`` (world, vehicle,
sv, drivers; why each value was chosen is in docs/world.md). The mechanism is
``bimacppo_common.config``: the packaged files are the only place a default is written
(``WorldConfig()`` is the packaged world, vehicle and SV model), a user's file lists only what
it changes, and an unknown key (with the nearest known one suggested), a wrong type or an
out-of-range value is a ``ConfigError`` (a ``ValueError``) naming the file and the dotted key,
because a typo would otherwise silently change the experiment.
"""
from __future__ import annotations

import pathlib
from typing import Mapping

from bimacppo_common import config
from bimacppo_common.config import ConfigError, Packaged, config_class, invalid, setting

__all__ = ["WorldConfig", "VehicleConfig", "SVConfig", "StylesConfig", "StyleConfig", "DriverConfig",
           "ConfigError", "STYLES", "CONFIG_DIR"]

WORLD_YAML = Packaged("bimacppo_sim", "config/world.yaml")
VEHICLE_YAML = Packaged("bimacppo_sim", "config/vehicle.yaml")
SV_YAML = Packaged("bimacppo_sim", "config/sv.yaml")
DRIVERS_YAML = Packaged("bimacppo_sim", "config/drivers.yaml")
CONFIG_DIR = pathlib.Path(WORLD_YAML.path).parent
STYLES = ("aggressive", "moderate", "conservative")


class _Nested(Packaged):
    """A mapping nested deeper than one section in a packaged file (``styles.<style>`` of
    sv.yaml): each style has defaults of its own under the same keys."""

    def __init__(self, outer: Packaged, *path: str):
        super().__init__(outer.package, outer.resource)
        self._outer, self._path = outer, path

    def data(self) -> dict:
        return self._outer.data()

    def section(self, name: str | None) -> Mapping:
        keys = (*self._path, *((name,) if name else ()))
        data: Mapping = self.data()
        for i, k in enumerate(keys):
            if not isinstance(data.get(k), Mapping):
                raise ConfigError("packaged defaults must be a mapping", source=self.path, key=keys[:i + 1])
            data = data[k]
        return data


def _order(cfg, lo: str, hi: str) -> None:
    """The cross-key rule ``lo <= hi`` of a [min, max] pair."""
    if getattr(cfg, lo) > getattr(cfg, hi):
        raise invalid(hi, f"must be >= key '{lo}' ({getattr(cfg, lo)}), got {getattr(cfg, hi)}")


@config_class(VEHICLE_YAML)
class VehicleConfig:
    """EV geometry and physical input limits (Tesla Model 3, paper §II-B)."""

    wheelbase: float = setting(lo=0.5, hi=10.0)
    length: float = setting(lo=0.5, hi=20.0)
    width: float = setting(lo=0.3, hi=5.0)
    a_min: float = setting(lo=-20.0, hi=0.0)
    a_max: float = setting(lo=0.0, hi=20.0)
    delta_max: float = setting(lo=0.0, hi=1.5)
    v_min: float = setting(lo=0.0, hi=50.0)
    v_max: float = setting(lo=0.0, hi=50.0)

    def _check(self) -> None:
        _order(self, "v_min", "v_max")

    @classmethod
    def load(cls, path: str | pathlib.Path | None = None) -> "VehicleConfig":
        """The packaged vehicle.yaml, overlaid by the YAML at ``path`` (only what it changes)."""
        return config.load(cls, path)


class StyleConfig:
    """One hidden SV driving style: IDM parameters plus gap acceptance. Each style of
    :data:`STYLES` is its own config class (its defaults are its own block of sv.yaml); they
    share these keys and this base, so ``isinstance(style, StyleConfig)`` holds for each."""


def _style_class(style: str) -> type:
    class Style(StyleConfig):
        probability: float = setting(lo=0.0, hi=1.0)
        v_desired: float = setting(lo=0.5, hi=30.0)
        a_max: float = setting(lo=0.1, hi=10.0)
        b_comfortable: float = setting(lo=0.1, hi=10.0)
        b_max: float = setting(lo=0.1, hi=15.0)
        time_headway: float = setting(lo=0.0, hi=5.0)
        min_gap: float = setting(lo=0.0, hi=10.0)
        sv_gap: float = setting(lo=0.0, hi=10.0)
        yield_to_ev: bool
        ev_gap: float = setting(lo=-5.0, hi=10.0)
        brake_for_crossing_ev: bool
        respects_fcfs: bool

    Style.__name__ = Style.__qualname__ = f"{style.capitalize()}Style"
    Style.__doc__ = f"The '{style}' SV style (sv.yaml, styles.{style})."
    return config_class(_Nested(SV_YAML, "styles", style))(Style)


AggressiveStyle, ModerateStyle, ConservativeStyle = (_style_class(s) for s in STYLES)


@config_class(SV_YAML, "styles")
class StylesConfig:
    """The styles an SV is drawn from; ``styles[name]`` is one of them."""

    aggressive: AggressiveStyle
    moderate: ModerateStyle
    conservative: ConservativeStyle

    def __getitem__(self, style: str) -> StyleConfig:
        if style not in STYLES:
            raise KeyError(style)
        return getattr(self, style)

    def values(self) -> tuple:
        return tuple(getattr(self, s) for s in STYLES)


@config_class(SV_YAML)
class SVConfig:
    """Surrounding-vehicle model and spawn distribution."""

    styles: StylesConfig
    idm_delta: float = setting(lo=1.0, hi=10.0)
    lateral_accel_max: float = setting(lo=0.5, hi=15.0)
    path_sample: float = setting(lo=0.05, hi=2.0)
    grid_cell: float = setting(lo=0.1, hi=2.0)
    grid_radius: float = setting(lo=0.2, hi=3.0)
    lookahead: float = setting(lo=5.0, hi=200.0)
    conflict_margin: float = setting(lo=0.0, hi=10.0)
    conflict_cap_after_exit: float = setting(lo=0.0, hi=30.0)
    stop_margin: float = setting(lo=0.0, hi=10.0)
    commit_margin: float = setting(lo=0.0, hi=20.0)
    creep_speed: float = setting(lo=0.0, hi=10.0)
    request_distance: float = setting(lo=1.0, hi=200.0)
    ev_prediction_horizon: float = setting(lo=0.0, hi=10.0)
    ev_prediction_step: float = setting(lo=0.05, hi=5.0)
    min_speed_for_eta: float = setting(lo=0.01, hi=5.0)
    spawn_time_jitter: float = setting(lo=0.0, hi=20.0)
    spawn_speed_factor_min: float = setting(lo=0.0, hi=1.5)
    spawn_speed_factor_max: float = setting(lo=0.0, hi=1.5)
    min_spawn_distance: float = setting(lo=0.0, hi=100.0)
    slow_speed_factor_min: float = setting(lo=0.01, hi=1.0)
    slow_speed_factor_max: float = setting(lo=0.01, hi=1.0)

    def _check(self) -> None:
        total = sum(s.probability for s in self.styles.values())
        if abs(total - 1.0) > 1e-6:
            raise invalid("styles", f"probabilities must sum to 1, got {total:g}")
        _order(self, "spawn_speed_factor_min", "spawn_speed_factor_max")
        _order(self, "slow_speed_factor_min", "slow_speed_factor_max")

    @classmethod
    def load(cls, path: str | pathlib.Path | None = None) -> "SVConfig":
        """The packaged sv.yaml, overlaid by the YAML at ``path`` (only what it changes)."""
        return config.load(cls, path)


@config_class(WORLD_YAML)
class WorldConfig:
    """Episode-level settings (world.yaml); ``vehicle`` and ``sv`` are sections whose defaults
    are vehicle.yaml and sv.yaml."""

    dt: float = setting(lo=1e-3, hi=1.0)
    time_limit: float = setting(lo=0.1, hi=3600.0)
    waypoint_spacing: float = setting(lo=0.5, hi=20.0)
    route_tail: float = setting(lo=0.0, hi=100.0)
    success_distance: float = setting(lo=0.0, hi=100.0)
    goal_any_lane: bool
    offroad_check: str = setting(choices=("corners", "centre", "off"))
    ev_start_distance_min: float = setting(lo=0.0, hi=500.0)
    ev_start_distance_max: float = setting(lo=0.0, hi=500.0)
    ev_speed_min: float = setting(lo=0.0, hi=30.0)
    ev_speed_max: float = setting(lo=0.0, hi=30.0)
    ev_nominal_speed: float = setting(lo=0.1, hi=30.0)
    graph_step: float = setting(lo=0.5, hi=20.0)
    lane_change_length: float = setting(lo=1.0, hi=100.0)
    lane_change_penalty: float = setting(lo=0.0, hi=1000.0)
    no_lane_change_zone: float = setting(lo=0.0, hi=100.0)
    vehicle: VehicleConfig
    sv: SVConfig

    def _check(self) -> None:
        _order(self, "ev_start_distance_min", "ev_start_distance_max")
        _order(self, "ev_speed_min", "ev_speed_max")

    @classmethod
    def load(cls, world: str | pathlib.Path | None = None, vehicle: str | pathlib.Path | None = None,
             sv: str | pathlib.Path | None = None) -> "WorldConfig":
        """The packaged world.yaml, vehicle.yaml and sv.yaml, each overlaid by the file given
        for it (it lists only what it changes). The vehicle and SV files hold those sections'
        keys at their top level; the world file may also change them under ``vehicle:`` and
        ``sv:``, and wins over the separate files."""
        layers = []
        if vehicle is not None:
            layers.append(({"vehicle": config.to_dict(VehicleConfig.load(vehicle))}, str(vehicle)))
        if sv is not None:
            layers.append(({"sv": config.to_dict(SVConfig.load(sv))}, str(sv)))
        if world is not None:
            layers.append(config.read_yaml(world))
        return config.build(cls, *layers)


@config_class(DRIVERS_YAML)
class DriverConfig:
    """Scripted reference EV drivers (go / yield)."""

    target_speed: float = setting(lo=0.1, hi=30.0)
    lookahead_min: float = setting(lo=0.5, hi=50.0)
    lookahead_time: float = setting(lo=0.0, hi=10.0)
    speed_gain: float = setting(lo=0.0, hi=20.0)
    stop_margin: float = setting(lo=0.0, hi=20.0)
    stop_decel: float = setting(lo=0.1, hi=10.0)
    safe_time_gap: float = setting(lo=0.0, hi=30.0)
    watch_distance: float = setting(lo=0.0, hi=500.0)

    @classmethod
    def load(cls, path: str | pathlib.Path | None = None) -> "DriverConfig":
        """The packaged drivers.yaml, overlaid by the YAML at ``path`` (only what it changes)."""
        return config.load(cls, path)
