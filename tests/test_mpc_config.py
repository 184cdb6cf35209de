"""MPCConfig: the packaged YAML loads, and every kind of bad file is a ValueError naming file and key."""
import pathlib

import pytest
import yaml

from bimacppo_mpc import MPCConfig
from bimacppo_mpc.config import DEFAULT_PATH


def _write(tmp_path, data) -> pathlib.Path:
    p = tmp_path / "mpc.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _base():
    return yaml.safe_load(DEFAULT_PATH.read_text())


def test_default_config_has_the_papers_weights_and_a_world_tick():
    cfg = MPCConfig.load()
    # eq. (33) weights, §IV-A
    assert cfg.q_x == (100.0, 100.0, 100.0, 20.0)
    assert cfg.q_u == (10.0, 10.0)
    assert cfg.q_du == (1.0, 1.0)
    assert cfg.wheelbase == pytest.approx(2.875)
    assert cfg.a_min < 0 < cfg.a_max and cfg.delta_min < 0 < cfg.delta_max and cfg.v_min < cfg.v_max
    assert cfg.brake_decel <= 0


def test_load_explicit_path_roundtrip(tmp_path):
    p = _write(tmp_path, _base())
    assert MPCConfig.load(p) == MPCConfig.load()


@pytest.mark.parametrize("mutate, key", [
    (lambda d: d.update(horizn=20), "horizn"),                       # unknown key
    (lambda d: d.pop("dt"), "dt"),                                   # missing key
    (lambda d: d.update(dt="0.1"), "dt"),                            # wrong type
    (lambda d: d.update(dt=-0.1), "dt"),                             # out of range
    (lambda d: d.update(horizon=2.5), "horizon"),
    (lambda d: d.update(q_x=[1, 2, 3]), "q_x"),
    (lambda d: d.update(q_u=[-1, 10]), "q_u[0]"),
    (lambda d: d.update(a_max=-1.0), "a_min/a_max"),
    (lambda d: d.update(v_min=20.0), "v_min/v_max"),
    (lambda d: d.update(brake_decel=1.0), "brake_decel"),
    (lambda d: d.update(relax_infeasible_speed_bounds="yes"), "relax_infeasible_speed_bounds"),
    (lambda d: d["fast"].update(hessian="bfgs"), "fast.hessian"),
    (lambda d: d["fast"].update(max_iter=-1), "fast.max_iter"),
    (lambda d: d["fast"].update(initial_guesses=["shifted", "magic"]), "fast.initial_guesses"),
    (lambda d: d["fast"].update(extra=1), "fast.extra"),
    (lambda d: d.pop("ipopt"), "ipopt"),
    (lambda d: d["ipopt"].update(tol=0), "ipopt.tol"),
])
def test_bad_values_name_file_and_key(tmp_path, mutate, key):
    d = _base()
    mutate(d)
    p = _write(tmp_path, d)
    with pytest.raises(ValueError) as err:
        MPCConfig.load(p)
    assert str(p) in str(err.value)
    assert key in str(err.value)


def test_unreadable_and_non_mapping_files(tmp_path):
    with pytest.raises(ValueError, match="cannot read"):
        MPCConfig.load(tmp_path / "missing.yaml")
    p = tmp_path / "list.yaml"
    p.write_text("- 1\n- 2\n")
    with pytest.raises(ValueError, match="mapping"):
        MPCConfig.load(p)


def test_replace_validates_and_accepts_nested_dicts():
    cfg = MPCConfig.load()
    assert cfg.replace(fast={"max_iter": 0}).fast.max_iter == 0
    assert cfg.replace(horizon=10).horizon == 10
    with pytest.raises(ValueError, match="horizon"):
        cfg.replace(horizon=0)
    with pytest.raises(ValueError, match="unknown"):
        cfg.replace(fast={"nope": 1})
    with pytest.raises(ValueError, match="unknown"):
        cfg.replace(nope=1)


def test_horizon_has_an_upper_bound():
    """A horizon of millions would make the controller's start-up hang instead of failing."""
    from bimacppo_mpc import MPCConfig
    from bimacppo_mpc.config import MAX_HORIZON

    cfg = MPCConfig.load()
    assert cfg.replace(horizon=MAX_HORIZON).horizon == MAX_HORIZON
    with pytest.raises(ValueError, match=r"horizon: must be <= 200"):
        cfg.replace(horizon=10_000_000)
