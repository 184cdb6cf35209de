"""The world's configuration on bimacppo_common.config: the packaged YAMLs are the only place of a
default, a user's file lists only what it changes, and a bad file is a ConfigError naming the
file and the dotted key."""
import dataclasses

import pytest
import yaml

from bimacppo_common import config
from bimacppo_common.config import ConfigError
from bimacppo_sim import World, WorldConfig, load_map
from bimacppo_sim.config import CONFIG_DIR, STYLES, DriverConfig, StyleConfig, SVConfig


def _packaged(name):
    return yaml.safe_load((CONFIG_DIR / name).read_text())


def _write(tmp_path, name, data):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return p


def test_defaults_are_the_packaged_files_and_frozen():
    c = WorldConfig.load()
    assert c == WorldConfig()
    world, vehicle, sv = _packaged("world.yaml"), _packaged("vehicle.yaml"), _packaged("sv.yaml")
    assert config.to_dict(c) == {**world, "vehicle": vehicle, "sv": sv}
    assert config.to_dict(DriverConfig.load()) == _packaged("drivers.yaml")
    assert c.sv.styles["moderate"].ev_gap == sv["styles"]["moderate"]["ev_gap"]
    assert all(isinstance(c.sv.styles[s], StyleConfig) for s in STYLES)
    with pytest.raises(KeyError):
        c.sv.styles["reckless"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.dt = 0.2


def test_an_overlay_lists_only_what_it_changes(tmp_path):
    base = WorldConfig.load()
    c = WorldConfig.load(world=_write(tmp_path, "world.yaml", {"time_limit": 12.5}),
                         vehicle=_write(tmp_path, "vehicle.yaml", {"v_max": 10.0}),
                         sv=_write(tmp_path, "sv.yaml", {"styles": {"moderate": {"v_desired": 7.5}}}))
    assert (c.time_limit, c.vehicle.v_max, c.sv.styles["moderate"].v_desired) == (12.5, 10.0, 7.5)
    assert dataclasses.replace(c, time_limit=base.time_limit, vehicle=base.vehicle, sv=base.sv) == base
    assert c.sv.styles["moderate"].ev_gap == base.sv.styles["moderate"].ev_gap
    assert c.sv.styles["aggressive"] == base.sv.styles["aggressive"]
    # the world file may change a section too, and wins over the section's own file
    c2 = WorldConfig.load(world=_write(tmp_path, "w2.yaml", {"vehicle": {"v_max": 9.0}}),
                          vehicle=_write(tmp_path, "vehicle.yaml", {"v_max": 10.0, "width": 2.0}))
    assert (c2.vehicle.v_max, c2.vehicle.width) == (9.0, 2.0)
    assert DriverConfig.load(_write(tmp_path, "drivers.yaml", {"target_speed": 6.0})) == \
        dataclasses.replace(DriverConfig.load(), target_speed=6.0)
    # an overlaid world runs
    World(load_map("dual_lane_4way"), c)


@pytest.mark.parametrize("name, load, data, key, hint", [
    ("world.yaml", lambda p: WorldConfig.load(world=p), {"time_limt": 5.0}, "time_limt", "time_limit"),
    ("world.yaml", lambda p: WorldConfig.load(world=p), {"vehicle": {"wheelbse": 2.0}}, "vehicle.wheelbse",
     "wheelbase"),
    ("vehicle.yaml", lambda p: WorldConfig.load(vehicle=p), {"wheelbse": 2.0}, "wheelbse", "wheelbase"),
    ("sv.yaml", lambda p: WorldConfig.load(sv=p), {"styles": {"moderat": {}}}, "styles.moderat", "moderate"),
    ("sv.yaml", lambda p: SVConfig.load(p), {"styles": {"moderate": {"ev_gapp": 1.0}}},
     "styles.moderate.ev_gapp", "ev_gap"),
    ("drivers.yaml", DriverConfig.load, {"target_sped": 5.0}, "target_sped", "target_speed"),
])
def test_an_unknown_key_is_refused_naming_file_and_key(tmp_path, name, load, data, key, hint):
    p = _write(tmp_path, name, data)
    with pytest.raises(ConfigError) as e:
        load(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}: unknown key '{key}'") and f"did you mean '{hint}'" in msg


@pytest.mark.parametrize("changes, key", [
    ({"dt": -0.1}, "dt"),
    ({"dt": "fast"}, "dt"),
    ({"goal_any_lane": "yes"}, "goal_any_lane"),
    ({"offroad_check": "wheels"}, "offroad_check"),
    ({"ev_speed_min": 9.0}, "ev_speed_max"),
    ({"vehicle": {"v_min": 20.0}}, "vehicle.v_max"),
])
def test_bad_world_values_name_file_and_key(tmp_path, changes, key):
    p = _write(tmp_path, "world.yaml", changes)
    with pytest.raises(ConfigError) as e:
        WorldConfig.load(world=p)
    assert str(e.value).startswith(f"{p}: key '{key}' ")


def test_bad_sv_and_vehicle_values_name_file_and_key(tmp_path):
    p = _write(tmp_path, "sv.yaml", {"styles": {"moderate": {"probability": 0.9}}})
    with pytest.raises(ConfigError, match="key 'styles' probabilities must sum to 1") as e:
        WorldConfig.load(sv=p)
    assert str(p) in str(e.value)
    p = _write(tmp_path, "sv.yaml", {"styles": {"aggressive": {"yield_to_ev": 1}}})
    with pytest.raises(ConfigError) as e:
        WorldConfig.load(sv=p)
    assert str(e.value).startswith(f"{p}: key 'styles.aggressive.yield_to_ev' must be true or false")
    p = _write(tmp_path, "vehicle.yaml", {"v_min": 13.0})
    with pytest.raises(ConfigError) as e:
        WorldConfig.load(vehicle=p)
    assert str(e.value).startswith(f"{p}: key 'v_max' must be >= key 'v_min'")
    with pytest.raises(ConfigError, match="key 'spawn_speed_factor_max'"):
        dataclasses.replace(SVConfig(), spawn_speed_factor_min=1.2)


@pytest.mark.parametrize("text, what", [
    ("dt: [0.1\n", "not valid YAML"),
    ("- 1\n- 2\n", "top level must be a mapping"),
])
def test_a_broken_yaml_is_a_config_error(tmp_path, text, what):
    for name, load in (("world.yaml", lambda p: WorldConfig.load(world=p)),
                       ("sv.yaml", lambda p: WorldConfig.load(sv=p)),
                       ("drivers.yaml", DriverConfig.load)):
        p = _write(tmp_path, name, text)
        with pytest.raises(ConfigError, match=what) as e:
            load(p)
        assert str(e.value).startswith(f"{p}: ")
    with pytest.raises(ConfigError, match="cannot read config file"):
        WorldConfig.load(world=tmp_path / "missing.yaml")
