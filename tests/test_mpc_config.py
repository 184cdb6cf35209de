"""MPCConfig on bimacppo_common.config: the packaged YAML is the only place of a default, a
user's file overlays it, and every kind of bad file is a ConfigError naming file and key."""
import dataclasses
import pathlib

import pytest
import yaml

from bimacppo_common.config import ConfigError
from bimacppo_mpc import MPCConfig
from bimacppo_mpc.config import DEFAULT_PATH, MAX_HORIZON


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
    assert cfg.source == str(DEFAULT_PATH)


def test_the_class_defaults_are_the_packaged_file():
    assert MPCConfig().to_dict() == MPCConfig.load().to_dict() == MPCConfig.from_dict(_base()).to_dict()
    assert MPCConfig().to_dict() == yaml.safe_load(DEFAULT_PATH.read_text())


def test_load_explicit_path_roundtrip(tmp_path):
    p = _write(tmp_path, _base())
    cfg = MPCConfig.load(p)
    assert cfg.source == str(p)
    assert dataclasses.replace(cfg, source="x") == dataclasses.replace(MPCConfig.load(), source="x")


def test_a_file_lists_only_what_it_changes(tmp_path):
    p = _write(tmp_path, {"horizon": 10, "fast": {"max_iter": 5}})
    cfg = MPCConfig.load(p)
    base = MPCConfig.load()
    assert (cfg.horizon, cfg.fast.max_iter) == (10, 5)
    assert cfg.dt == base.dt and cfg.fast.tol == base.fast.tol and cfg.ipopt == base.ipopt
    assert MPCConfig.load(_write(tmp_path, {"steer_rate_max": None})).steer_rate_max is None


@pytest.mark.parametrize("mutate, key", [
    (lambda d: d.update(dt="0.1"), "'dt'"),                           # wrong type
    (lambda d: d.update(dt=-0.1), "'dt'"),                            # out of range
    (lambda d: d.update(horizon=2.5), "'horizon'"),
    (lambda d: d.update(q_x=[1, 2, 3]), "'q_x'"),
    (lambda d: d.update(q_u=[-1, 10]), "'q_u'"),
    (lambda d: d.update(a_max=-1.0), "'a_max'"),
    (lambda d: d.update(v_min=20.0), "'v_max'"),
    (lambda d: d.update(q_u=[0, 10], q_du=[0, 1]), "'q_du'"),
    (lambda d: d.update(brake_decel=1.0), "'brake_decel'"),
    (lambda d: d.update(relax_infeasible_speed_bounds="yes"), "'relax_infeasible_speed_bounds'"),
    (lambda d: d.update(steer_rate_max=0), "'steer_rate_max'"),
    (lambda d: d["fast"].update(hessian="bfgs"), "'fast.hessian'"),
    (lambda d: d["fast"].update(max_iter=-1), "'fast.max_iter'"),
    (lambda d: d["fast"].update(initial_guesses=["shifted", "magic"]), "'fast.initial_guesses'"),
    (lambda d: d["fast"].update(initial_guesses=["hold", "hold"]), "'fast.initial_guesses'"),
    (lambda d: d.update(ipopt=5), "'ipopt'"),
    (lambda d: d["ipopt"].update(tol=0), "'ipopt.tol'"),
])
def test_bad_values_name_file_and_key(tmp_path, mutate, key):
    d = _base()
    mutate(d)
    p = _write(tmp_path, d)
    with pytest.raises(ConfigError) as err:
        MPCConfig.load(p)
    assert str(err.value).startswith(f"{p}: ")
    assert key in str(err.value)
    assert isinstance(err.value, ValueError)


@pytest.mark.parametrize("data, message", [
    ({"horizn": 20}, "unknown key 'horizn' (did you mean 'horizon'?)"),
    ({"fast": {"max_iters": 3}}, "unknown key 'fast.max_iters' (did you mean 'max_iter'?)"),
    ({"fast": {"extra": 1}}, "unknown key 'fast.extra'"),
])
def test_unknown_keys_are_refused_with_the_nearest_known_one(tmp_path, data, message):
    p = _write(tmp_path, data)
    with pytest.raises(ConfigError, match="^" + str(p).replace(".", r"\.") + ": ") as err:
        MPCConfig.load(p)
    assert message in str(err.value)


def test_unreadable_and_non_mapping_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        MPCConfig.load(tmp_path / "missing.yaml")
    p = tmp_path / "list.yaml"
    p.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        MPCConfig.load(p)


def test_replace_validates_and_accepts_nested_dicts():
    cfg = MPCConfig.load()
    assert cfg.replace(fast={"max_iter": 0}).fast.max_iter == 0
    assert cfg.replace(fast={"max_iter": 0}).fast.tol == cfg.fast.tol      # the rest of the section stays
    assert cfg.replace(horizon=10).horizon == 10
    assert cfg.replace(fast=cfg.fast) == cfg
    with pytest.raises(ValueError, match="horizon"):
        cfg.replace(horizon=0)
    with pytest.raises(ValueError, match="unknown key 'fast.nope'"):
        cfg.replace(fast={"nope": 1})
    with pytest.raises(ValueError, match="unknown key 'nope'"):
        cfg.replace(nope=1)
    with pytest.raises(ValueError, match="key 'a_max'"):
        dataclasses.replace(cfg, a_max=-1.0)            # direct construction is checked too


def test_horizon_has_an_upper_bound():
    """A horizon of millions would make the controller's start-up hang instead of failing."""
    cfg = MPCConfig.load()
    assert cfg.replace(horizon=MAX_HORIZON).horizon == MAX_HORIZON
    with pytest.raises(ValueError, match=r"key 'horizon' must be in \[1, 200\]"):
        cfg.replace(horizon=10_000_000)


def test_importing_the_mpc_makes_idle_openmp_threads_passive_unless_the_user_chose():
    """Importing bimacppo_mpc sets OMP_WAIT_POLICY=PASSIVE (through bimacppo_common, which it
    imports first) before numba's OpenMP runtime loads (spinning threads make concurrent training
    runs on shared cores several times slower), and keeps a value the user set; the parallel
    batch solve still runs and agrees with the serial one."""
    import os
    import subprocess
    import sys
    script = ("import os, numpy as np\n"
              "from bimacppo_mpc import MPCConfig, make_controller\n"
              "c = make_controller(MPCConfig.load(), 'fast')\n"
              "x = np.tile([0.0, 0.0, 5.0, 0.0], (8, 1)); r = np.tile([12.0, 1.0, 6.0, 0.1], (8, 1))\n"
              "u = np.zeros((8, 2)); a = c.solve_batch(x, r, u).u\n"
              "c.reset(); c.set_threads(1); b = c.solve_batch(x, r, u).u\n"
              "assert np.allclose(a, b), (a, b)\n"
              "print(os.environ['OMP_WAIT_POLICY'])\n")
    base = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    for env, want in ((base, "PASSIVE"), ({**base, "OMP_WAIT_POLICY": "ACTIVE"}, "ACTIVE")):
        out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        assert out.stdout.split()[-1] == want
