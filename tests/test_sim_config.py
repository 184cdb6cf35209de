"""Config files load into frozen dataclasses; bad values fail naming file and key."""
import dataclasses

import pytest
import yaml

from bimacppo_sim import WorldConfig
from bimacppo_sim.config import CONFIG_DIR, DriverConfig


def test_defaults_load_and_are_frozen():
    c = WorldConfig.load()
    assert c.dt == 0.1 and c.waypoint_spacing == 3.0
    assert c.vehicle.wheelbase == 2.875 and (c.vehicle.length, c.vehicle.width) == (4.69, 1.85)
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.dt = 0.2
    assert DriverConfig.load().target_speed == 8.0


def _variant(tmp_path, name, **changes):
    data = yaml.safe_load((CONFIG_DIR / name).read_text())
    data.update(changes)
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


@pytest.mark.parametrize("changes, msg", [
    ({"dt": -0.1}, "'dt'.*out of range"),
    ({"dt": "fast"}, "'dt' must be a number"),
    ({"goal_any_lane": "yes"}, "goal_any_lane"),
    ({"offroad_check": "wheels"}, "offroad_check"),
    ({"typo_key": 1}, "unknown key"),
    ({"ev_speed_min": 9.0}, "ev_speed_min must be <="),
])
def test_world_yaml_errors(tmp_path, changes, msg):
    p = _variant(tmp_path, "world.yaml", **changes)
    with pytest.raises(ValueError, match=msg) as e:
        WorldConfig.load(world=p)
    assert "world.yaml" in str(e.value)


def test_sv_yaml_errors(tmp_path):
    data = yaml.safe_load((CONFIG_DIR / "sv.yaml").read_text())
    data["styles"]["moderate"]["probability"] = 0.9
    p = tmp_path / "sv.yaml"
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match="sum to 1"):
        WorldConfig.load(sv=p)
    del data["styles"]["moderate"]
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match="styles"):
        WorldConfig.load(sv=p)


def test_missing_key_is_named(tmp_path):
    data = yaml.safe_load((CONFIG_DIR / "vehicle.yaml").read_text())
    del data["wheelbase"]
    p = tmp_path / "vehicle.yaml"
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match="missing key 'wheelbase'"):
        WorldConfig.load(vehicle=p)
