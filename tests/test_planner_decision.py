"""Observation (eq. 18-20) and action decoding (§III-C) on plain arrays."""
import math
from collections import Counter

import numpy as np
import pytest

from bimacppo_common.conventions import wrap_angle
from conftest import REPO
from bimacppo_planner.decision import (ActionConfig, ConfigError, EnvConfig, ObservationConfig, WaypointTracker,
                                       decode_action, observe)

REPO_ENV_JUNCTION = REPO / "studies/config/env_wait_chord_junction_road.yaml"


def test_wrap_angle_stays_in_half_open_interval():
    for a in np.linspace(-20, 20, 401):
        w = wrap_angle(float(a))
        assert -math.pi < w <= math.pi + 1e-12
        assert math.isclose(math.sin(w), math.sin(a), abs_tol=1e-9)
        assert math.isclose(math.cos(w), math.cos(a), abs_tol=1e-9)
    assert wrap_angle(math.pi) == pytest.approx(math.pi)
    assert wrap_angle(-math.pi) == pytest.approx(math.pi)


def test_observation_follows_eq_18_to_20():
    cfg = ObservationConfig(max_sv=3, sv_clip=7.5)
    ego = np.array([1.0, -20.0, 5.0, math.pi / 2])
    goal = np.array([-30.0, 5.0, math.pi])
    svs = np.array([[3.0, -18.0, 7.0, -math.pi / 2],     # near: dx=2, dy=2
                    [40.0, 0.0, 0.0, 3.0]])               # far: clipped
    o = observe(cfg, ego, goal, svs)
    assert o.shape == (16,) and o.dtype == np.float32
    np.testing.assert_allclose(o[:4], [31.0, 25.0, 5.0, wrap_angle(math.pi / 2 - math.pi)], rtol=1e-6)
    np.testing.assert_allclose(o[4:8], [2.0, 2.0, -2.0, wrap_angle(math.pi)], rtol=1e-6)
    np.testing.assert_allclose(o[8:12], [7.5, 7.5, 5.0, wrap_angle(math.pi / 2 - 3.0)], rtol=1e-6)
    np.testing.assert_allclose(o[12:16], cfg.pad_value)


def test_observation_sorts_svs_nearest_first_and_drops_extra():
    cfg = ObservationConfig(max_sv=1)
    ego = np.zeros(4)
    svs = np.array([[5.0, 0.0, 1.0, 0.0], [1.0, 1.0, 2.0, 0.0]])
    o = observe(cfg, ego, np.zeros(3), svs)
    assert o.shape == (8,)
    assert o[4] == pytest.approx(1.0) and o[6] == pytest.approx(-2.0)


def _straight_route(n=20, spacing=3.0):
    ys = np.arange(n) * spacing
    return np.stack([np.zeros(n), ys, np.full(n, math.pi / 2)], axis=1)


def test_tracker_drops_waypoints_behind_and_offers_next_five():
    tr = WaypointTracker(_straight_route(), 5)
    tr.update(0.0, 7.0)
    c = tr.candidates()
    np.testing.assert_allclose(c[:, 1], [9, 12, 15, 18, 21])
    tr.update(0.0, 0.0)   # going back does not resurrect passed waypoints
    np.testing.assert_allclose(tr.candidates()[0, 1], 9)
    tr.update(0.0, 100.0)  # past the end: the last waypoint repeats
    np.testing.assert_allclose(tr.candidates()[:, 1], [57] * 5)


def test_tracker_rejects_bad_routes():
    with pytest.raises(ValueError, match="route"):
        WaypointTracker(np.zeros((0, 3)), 5)
    with pytest.raises(ValueError, match="route"):
        WaypointTracker(np.array([[0.0, np.nan, 0.0]]), 5)


def test_decode_action_speed_waypoint_and_lane_change():
    cfg = EnvConfig.load().action
    tr = WaypointTracker(_straight_route(), cfg.n_waypoints)
    tr.update(0.0, 0.5)

    def lateral(x, y, psi, side):
        return (x - 3.5 * side * math.sin(psi + math.pi), y, psi) if side == -1 else None

    x, changed = decode_action([2, 4, 1], tr, cfg, lateral)
    np.testing.assert_allclose(x, [0.0, 9.0, 8.0, math.pi / 2])
    assert not changed
    x, changed = decode_action([0, 0, 0], tr, cfg, lateral)   # left: the adjacent lane exists
    assert changed and x[2] == 0.0 and x[1] == pytest.approx(3.0) and x[0] != 0.0
    x, changed = decode_action([0, 0, 2], tr, cfg, lateral)   # right: no lane there -> keep
    assert not changed and x[0] == 0.0
    with pytest.raises(ValueError, match="outside"):
        decode_action([5, 0, 0], tr, cfg, lateral)


def test_env_config_defaults_and_errors(tmp_path):
    cfg = EnvConfig.load()
    assert cfg.nvec == (5, 5, 3)
    assert cfg.action.speeds == (0.0, 2.0, 4.0, 6.0, 8.0)
    assert cfg.obs_dim == 16
    assert EnvConfig.from_dict(cfg.to_dict()) == cfg
    bad = tmp_path / "env.yaml"
    bad.write_text("reward:\n  alpah1: 3\n")
    with pytest.raises(ConfigError, match=r"reward\.alpah1"):
        EnvConfig.load(bad)
    bad.write_text("reward: [1, 2\n")
    with pytest.raises(ConfigError, match="YAML"):
        EnvConfig.load(bad)
    bad.write_text("action:\n  speeds: [0, .nan]\n")
    with pytest.raises(ConfigError, match="speeds"):
        EnvConfig.load(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        EnvConfig.load(tmp_path / "missing.yaml")
    assert EnvConfig.load(overrides={"reward.step": -0.5}).reward.step == -0.5
    bad.write_text("reward:\n  alpha4: 1.0\n")                  # a penalty must stay <= 0
    with pytest.raises(ConfigError, match=r"env\.yaml: key 'reward\.alpha4' must be <= 0"):
        EnvConfig.load(bad)
    with pytest.raises(ConfigError, match=r"overrides: unknown key 'reward\.stepp' \(did you mean 'step'\?\)"):
        EnvConfig.load(overrides={"reward.stepp": -0.5})


VARIANTS = {   # variant file -> what it changes relative to the packaged env.yaml, and nothing else
    "bimacppo_learning/bimacppo_learning/config/env_ego.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 30.0, "pad_value": [30.0, 30.0, 0.0, 0.0]}},
    "bimacppo_learning/bimacppo_learning/config/env_extended.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 30.0, "pad_value": [30.0, 30.0, 0.0, 0.0]},
         "action": {"decision_every": 3}},
    "bimacppo_learning/bimacppo_learning/config/env_yield.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 30.0, "pad_value": [30.0, 30.0, 0.0, 0.0]},
         "action": {"decision_every": 3}, "reward": {"timeout_mode": "truncate", "threat_entry": -10.0}},
    "bimacppo_learning/bimacppo_learning/config/env_yield_hold.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 30.0, "pad_value": [30.0, 30.0, 0.0, 0.0]},
         "action": {"decision_every": 3, "zero_speed": "hold"},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0}},
    "bimacppo_learning/bimacppo_learning/config/env_yield_go.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 30.0, "pad_value": [30.0, 30.0, 0.0, 0.0]},
         "action": {"decision_every": 3},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "idle_clear": -0.1}},
    "bimacppo_learning/bimacppo_learning/config/env_yield_far.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0]},
         "action": {"decision_every": 3}, "reward": {"timeout_mode": "truncate", "threat_entry": -10.0}},
    "bimacppo_learning/bimacppo_learning/config/env_yield_wait.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0]},
         "action": {"decision_every": 3, "zero_speed": "hold"},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "threat_speed": -1.0, "idle_clear": -0.1}},
    "studies/config/env_far_idle_clear.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0]}, "action": {"decision_every": 3},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "idle_clear": -0.1}},
    "studies/config/env_far_hold_idle_clear.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0]}, "action": {"decision_every": 3, "zero_speed": "hold"},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "idle_clear": -0.1}},
    "studies/config/env_far_threat_speed.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0]}, "action": {"decision_every": 3},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "threat_speed": -1.0, "idle_clear": -0.1}},
    "studies/config/env_far_chord.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0]},
         "action": {"decision_every": 3, "chord_tol": 1.0}, "reward": {"timeout_mode": "truncate", "threat_entry": -10.0}},
    "studies/config/env_wait_chord.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0]},
         "action": {"decision_every": 3, "zero_speed": "hold", "chord_tol": 1.0},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "threat_speed": -1.0, "idle_clear": -0.1}},
    "studies/config/env_wait_chord_go.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0]},
         "action": {"decision_every": 3, "zero_speed": "hold", "chord_tol": 1.0},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "threat_speed": -1.0, "idle_clear": -0.1,
                    "go_speed": 4.0}},
    "studies/config/env_wait_chord_look.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0]},
         "action": {"decision_every": 3, "zero_speed": "hold", "chord_tol": 1.0, "min_lookahead": 4.0},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "threat_speed": -1.0, "idle_clear": -0.1}},
    "studies/config/env_wait_chord_look_go.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0]},
         "action": {"decision_every": 3, "zero_speed": "hold", "chord_tol": 1.0, "min_lookahead": 4.0},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "threat_speed": -1.0, "idle_clear": -0.1,
                    "go_speed": 4.0}},
    "studies/config/env_wait_chord_junction.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0], "junction": True},
         "action": {"decision_every": 3, "zero_speed": "hold", "chord_tol": 1.0},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "threat_speed": -1.0, "idle_clear": -0.1}},
    "studies/config/env_wait_chord_junction_road.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0], "junction": True},
         "action": {"decision_every": 3, "zero_speed": "hold", "chord_tol": 1.0, "chord_rule": "road"},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "threat_speed": -1.0, "idle_clear": -0.1}},
    "studies/config/env_wait_chord_road.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0]},
         "action": {"decision_every": 3, "zero_speed": "hold", "chord_tol": 1.0, "chord_rule": "road"},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "threat_speed": -1.0, "idle_clear": -0.1}},
    "studies/config/env_wait_chord_junction_road_overtake.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0], "junction": True},
         "action": {"decision_every": 3, "zero_speed": "hold", "chord_tol": 1.0, "chord_rule": "road"},
         "reward": {"threat_entry": -10.0, "threat_speed": -1.0, "idle_clear": -0.1}},
    "studies/config/env_wait_chord_junction_road_overtake_go.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0], "junction": True},
         "action": {"decision_every": 3, "zero_speed": "hold", "chord_tol": 1.0, "chord_rule": "road"},
         "reward": {"threat_entry": -10.0, "threat_speed": -1.0, "idle_clear": -0.1, "go_speed": 4.0}},
    "studies/config/env_wait_chord_junction_road_stop.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0], "junction": True},
         "action": {"decision_every": 3, "zero_speed": "hold", "hold_decel": 4.0, "chord_tol": 1.0, "chord_rule": "road"},
         "reward": {"timeout_mode": "truncate", "threat_entry": -10.0, "threat_speed": -1.0, "idle_clear": -0.1}},
    "studies/config/env_extended_safe.yaml":
        {"observation": {"sv_frame": "ego", "sv_clip": 30.0, "pad_value": [30.0, 30.0, 0.0, 0.0]},
         "action": {"decision_every": 3}, "reward": {"collision_base": -30.0}},
}


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_variant_files_overlay_the_packaged_env_yaml(variant):
    import yaml
    from conftest import REPO
    path = REPO / variant
    assert yaml.safe_load(path.read_text()) == VARIANTS[variant]          # lists only its changes
    assert path.read_text().startswith("# Overlays bimacppo_planner/config/env.yaml")
    expect = EnvConfig.load().to_dict()
    for sec, keys in VARIANTS[variant].items():
        expect[sec].update(keys)
    assert EnvConfig.load(path).to_dict() == expect


def test_every_study_env_file_is_an_overlay_of_the_packaged_env_yaml():
    """Every studies/config/env_*.yaml says it overlays env.yaml and loads to the packaged
    defaults with exactly its own keys changed (the files not listed above included)."""
    import yaml
    from conftest import REPO
    files = sorted((REPO / "studies/config").glob("env_*.yaml"))
    assert len(files) > len(VARIANTS) // 2
    for path in files:
        assert path.read_text().startswith("# Overlays bimacppo_planner/config/env.yaml"), path.name
        expect = EnvConfig.load().to_dict()
        for sec, keys in yaml.safe_load(path.read_text()).items():
            expect[sec].update({k: list(v) if isinstance(v, list) else v for k, v in keys.items()})
        got = EnvConfig.load(path).to_dict()
        assert got == expect, path.name


def test_saved_env_config_round_trips_and_older_dicts_take_packaged_defaults():
    import dataclasses
    cfg = EnvConfig.load(overrides={"observation": {"max_sv": 2}, "action.decision_every": 2})
    saved = cfg.to_dict()
    assert EnvConfig.from_dict(saved, where="policy.pt") == cfg
    del saved["observation"]["sv_frame"], saved["reward"]                 # saved before those keys existed
    old = EnvConfig.from_dict(saved, where="policy.pt")
    assert old.observation.sv_frame == EnvConfig.load().observation.sv_frame and old.reward == EnvConfig.load().reward
    assert (old.observation.max_sv, old.action.decision_every) == (2, 2)
    with pytest.raises(ConfigError, match=r"policy\.pt: key 'action\.n_waypoints' must be >= 1, got 0"):
        EnvConfig.from_dict({"action": {"n_waypoints": 0}}, where="policy.pt")
    assert ObservationConfig() == EnvConfig.load().observation           # class defaults = env.yaml
    with pytest.raises(ValueError, match="max_sv"):
        dataclasses.replace(ObservationConfig(), max_sv=-1)


def test_ego_frame_observation_keeps_sides():
    cfg = ObservationConfig(max_sv=2, sv_clip=30.0, sv_frame="ego", pad_value=(30.0, 30.0, 0.0, 0.0))
    ego = np.array([0.0, 0.0, 4.0, math.pi / 2])          # heading north
    svs = np.array([[-10.0, 5.0, 8.0, 0.0],                 # ahead-left, crossing eastwards
                    [3.0, -2.0, 4.0, math.pi / 2]])         # behind-right
    o = observe(cfg, ego, np.array([0.0, 50.0, math.pi / 2]), svs)
    # nearest first: the behind-right SV (dist 3.6), then ahead-left (dist 11.2)
    np.testing.assert_allclose(o[4:6], [-2.0, -3.0], atol=1e-6)
    np.testing.assert_allclose(o[8:10], [5.0, 10.0], atol=1e-6)
    with pytest.raises(ConfigError, match="sv_frame"):
        EnvConfig.from_dict({"observation": {"sv_frame": "polar"}})


def test_timeout_pays_the_failure_terms_only_when_terminal():
    from bimacppo_planner.decision import step_reward
    term = EnvConfig.load().reward
    trunc = EnvConfig.load(overrides={"reward.timeout_mode": "truncate"}).reward
    assert term.timeout_terminal and not trunc.timeout_terminal
    cut = step_reward(trunc, False, "timeout", 3, 2, 0.0, 4.0)
    assert cut == pytest.approx(trunc.step)                               # a cut episode: step terms only
    failed = step_reward(term, False, "timeout", 3, 2, 0.0, 4.0)
    assert failed == pytest.approx(term.step + term.timeout + min(term.r_f_max, term.alpha3 / 4.0))
    # the other outcomes do not depend on the mode
    for outcome in ("success", "collision"):
        assert step_reward(term, True, outcome, 2, 1, 5.0, 3.0) == step_reward(trunc, True, outcome, 2, 1, 5.0, 3.0)
    with pytest.raises(ConfigError, match=r"timeout_mode"):
        EnvConfig.load(overrides={"reward.timeout_mode": "bootstrap"})
    with pytest.raises(ConfigError, match=r"threat_entry.*<= 0"):
        EnvConfig.load(overrides={"reward.threat_entry": 1.0})


def test_hold_decodes_a_zero_speed_to_the_ev_position_facing_along_the_route():
    # a route that turns: WP0's heading differs from the EV's own, and hold takes the route's
    route = np.array([[0.0, float(y), math.pi / 2 + 0.02 * y] for y in range(0, 40, 3)])
    tr = WaypointTracker(route, 5)
    tr.update(0.0, 1.0)
    ego = np.array([0.2, 1.0, 6.0, 1.5])
    lateral = lambda x, y, psi, side: (x - 3.5 * side, y, psi)     # noqa: E731
    paper = ActionConfig(n_waypoints=5, speeds=(0.0, 2.0, 4.0, 6.0, 8.0), lane_change=(-1, 0, 1),
                         decision_every=3, zero_speed="waypoint")
    hold = dataclasses_replace(paper, zero_speed="hold")
    for a1 in range(5):
        for a3 in range(3):
            x, changed = decode_action([a1, 0, a3], tr, hold, lateral, ego)
            np.testing.assert_array_equal(x, [0.2, 1.0, 0.0, tr.candidates()[0][2]])
            assert x[3] != ego[3]
            assert not changed
            xp, _ = decode_action([a1, 0, a3], tr, paper, lateral, ego)      # the paper: the waypoint at 0 m/s
            assert xp[2] == 0.0 and xp[1] == pytest.approx(tr.candidates()[a1][1])
    # other speeds decode the same in both modes
    np.testing.assert_array_equal(decode_action([3, 2, 1], tr, hold, lateral, ego)[0],
                                  decode_action([3, 2, 1], tr, paper, lateral, ego)[0])
    with pytest.raises(ValueError, match="needs the EV pose"):
        decode_action([0, 0, 1], tr, hold, lateral)


def dataclasses_replace(obj, **kw):
    import dataclasses
    return dataclasses.replace(obj, **kw)


def _turning_route(radius=8.0, spacing=3.0):
    """10 m straight north, then a quarter circle to the right (east), then straight east."""
    pts = [(0.0, float(y), math.pi / 2) for y in np.arange(-12.0, 0.0, spacing)]
    n = int(round(radius * math.pi / 2 / spacing))
    for k in range(n + 1):
        th = math.pi - k * (math.pi / 2) / n            # on the circle around (radius, 0)
        pts.append((radius + radius * math.cos(th), radius * math.sin(th), th - math.pi / 2))
    x_end, y_end = pts[-1][0], pts[-1][1]
    pts += [(x_end + spacing * k, y_end, 0.0) for k in range(1, 6)]
    return np.array(pts)


def _dense_deviation(route, i0, j, x, y):
    """Largest distance from the chord (x, y) -> route[j] of the route polyline from route[i0]
    to route[j], sampled densely (independent of the vertex rule under test)."""
    a, b = np.array([x, y]), route[j, :2]
    d = b - a
    worst = 0.0
    for i in range(i0, j):
        for t in np.linspace(0.0, 1.0, 21):
            p = route[i, :2] + t * (route[i + 1, :2] - route[i, :2]) - a
            u = min(max(float(p @ d) / float(d @ d), 0.0), 1.0)
            worst = max(worst, float(np.hypot(*(p - u * d))))
    return worst


@pytest.mark.parametrize("tol", [0.3, 1.0, 2.5])
def test_chord_limit_folds_far_waypoints_back_only_where_the_route_turns(tol):
    route = _turning_route()
    lateral = lambda x, y, psi, side: (x - 3.5 * side, y, psi)     # noqa: E731
    paper = ActionConfig(n_waypoints=5, speeds=(0.0, 2.0, 4.0, 6.0, 8.0), lane_change=(-1, 0, 1),
                         decision_every=3, zero_speed="waypoint")
    chord = dataclasses_replace(paper, chord_tol=tol)
    folded = 0
    for y0 in np.arange(-11.0, 9.0, 0.7):
        tr = WaypointTracker(route, 5)
        # the EV on the route: on the straight part, then on the arc
        if y0 < 0.0:
            x, y = 0.0, y0
        else:
            th = math.pi - min(y0 / 8.0, 1.0) * math.pi / 2
            x, y = 8.0 + 8.0 * math.cos(th), 8.0 * math.sin(th)
        tr.update(x, y)
        ego = np.array([x, y, 5.0, 1.0])
        for a1 in range(5):
            got, _ = decode_action([a1, 2, 1], tr, chord, lateral, ego)
            k = next(k for k in range(5) if np.allclose(tr.candidates()[k][[0, 1]], got[[0, 1]]))
            assert k <= a1
            m = len(route) - 1
            dev = lambda kk: _dense_deviation(route, tr.idx, min(tr.idx + kk, m), x, y)  # noqa: E731
            if k > 0:
                assert dev(k) <= tol + 1e-9          # the chosen chord keeps to the route
            if k < a1:
                folded += 1
                assert dev(k + 1) > tol - 1e-9       # and the next one out would not
            # lane changes still apply to the folded waypoint
            lc, changed = decode_action([a1, 2, 0], tr, chord, lateral, ego)
            assert changed and lc[0] == pytest.approx(got[0] + 3.5)
        # on the straight approach, far from the turn, nothing changes
        if y0 < -11.0 + 0.7 * 2:
            for a1 in range(3):
                np.testing.assert_array_equal(decode_action([a1, 3, 1], tr, chord, lateral, ego)[0],
                                              decode_action([a1, 3, 1], tr, paper, lateral, ego)[0])
    assert folded > 0                                # the turn does fold waypoints back
    with pytest.raises(ValueError, match="needs the EV pose"):
        decode_action([4, 2, 1], WaypointTracker(route, 5), chord, lateral)
    with pytest.raises(ConfigError, match="chord_tol"):
        EnvConfig.load(overrides={"action.chord_tol": 0.0})


def test_chord_limit_keeps_a_constant_far_waypoint_on_the_road_in_the_empty_right_turn():
    """End to end through the env and the NMPC: WP4 held at 2 m/s in the right turn cuts across
    the kerb without the limit and turns with it."""
    from bimacppo_common.conventions import TASKS
    from bimacppo_learning.evaluate import evaluate
    from conftest import REPO

    class Constant:
        def act(self, obs):
            return np.array([4, 1, 1], np.int64)
    out = {}
    for name, path in (("paper", "bimacppo_learning/bimacppo_learning/config/env_yield_far.yaml"),
                       ("chord", "studies/config/env_far_chord.yaml")):
        cfg = EnvConfig.load(REPO / path)
        c = evaluate(Constant(), map_id="dual_lane_4way", n_svs=(0,), tasks=(TASKS.index("right"),), episodes=3,
                     workers=1, random_row=False, env_config=cfg, seed_set="validation")[0]
        out[name] = c.counts
    assert out["paper"].get("collision", 0) == 3
    assert out["chord"].get("success", 0) == 3


def test_min_lookahead_starts_a1_at_the_first_waypoint_that_far_ahead():
    plain, look = WaypointTracker(_straight_route(), 5), WaypointTracker(_straight_route(), 5, min_lookahead=4.0)
    for tr in (plain, look):
        tr.update(0.0, 7.0)
    np.testing.assert_allclose(plain.candidates()[:, 1], [9, 12, 15, 18, 21])
    np.testing.assert_allclose(look.candidates()[:, 1], [12, 15, 18, 21, 24])   # 9 is 2 m ahead: too close
    assert look.idx == plain.idx == 3          # passed waypoints are the same rule with or without
    look.update(0.0, 8.0)                      # exactly 4 m ahead counts as far enough
    np.testing.assert_allclose(look.candidates()[0, 1], 12)
    look.update(0.0, 100.0)                    # past the end: the last waypoint repeats
    np.testing.assert_allclose(look.candidates()[:, 1], [57] * 5)
    with pytest.raises(ValueError, match="min_lookahead"):
        WaypointTracker(_straight_route(), 5, min_lookahead=0.0)
    with pytest.raises(ValueError, match="min_lookahead"):
        WaypointTracker(_straight_route(), 5, min_lookahead=float("nan"))
    with pytest.raises(ConfigError, match="min_lookahead"):
        EnvConfig.load(overrides={"action.min_lookahead": -1.0})


def test_min_lookahead_bounds_the_turn_a_waypoint_asks_for_and_keeps_the_stop_in_place():
    """The EV anywhere across its lane and the next waypoint close ahead: without a look-ahead
    the aim from the EV to x_IMR can point almost sideways, with 4 m it stays within
    atan(lane width + half a lane / 4 m), whatever A1 and A3."""
    route = _straight_route()
    lateral = lambda x, y, psi, side: (x - 3.5 * side, y, psi)     # noqa: E731
    base = ActionConfig(n_waypoints=5, speeds=(0.0, 2.0, 4.0, 6.0, 8.0), lane_change=(-1, 0, 1),
                        decision_every=3, zero_speed="hold", chord_tol=1.0)
    worst = {}
    for L in (None, 4.0):
        cfg = dataclasses_replace(base, min_lookahead=L)
        w = 0.0
        for y in np.arange(0.0, 30.0, 0.25):
            for x in (-1.75, -0.5, 0.0, 0.5, 1.75):
                tr = WaypointTracker.for_action(route, cfg)
                assert tr.min_lookahead == L and tr.n == 5
                tr.update(x, y)
                ego = np.array([x, y, 0.5, math.pi / 2])
                for a1 in range(5):
                    for a3 in range(3):
                        got, _ = decode_action([a1, 1, a3], tr, cfg, lateral, ego)
                        ahead, side = got[1] - y, got[0] - x
                        w = max(w, math.degrees(math.atan2(abs(side), ahead)))
                        stop, _ = decode_action([a1, 0, a3], tr, cfg, lateral, ego)   # hold: unchanged
                        np.testing.assert_array_equal(stop, [x, y, 0.0, math.pi / 2])
        worst[L] = w
    assert worst[None] > 80.0
    assert worst[4.0] <= math.degrees(math.atan2(3.5 + 1.75, 4.0)) + 1e-9


def test_min_lookahead_lets_a_creeping_ev_reach_the_goal_on_the_empty_road():
    """End to end through the env and the NMPC: WP0 at 2 m/s with a lane change ordered left and
    right in turn stalls the EV short of every goal without the look-ahead; with it, it arrives."""
    from bimacppo_learning.evaluate import evaluate
    from conftest import REPO

    class Dither:
        def __init__(self):
            self.k = 0

        def begin_episode(self, seed):
            self.k = 0

        def act(self, obs):
            self.k += 1
            return np.array([0, 1, (0, 2)[self.k % 2]], np.int64)

    out = {}
    for name in ("env_wait_chord", "env_wait_chord_look"):
        cfg = EnvConfig.load(REPO / "studies" / "config" / f"{name}.yaml")
        cells = evaluate(Dither(), map_id="dual_lane_4way", n_svs=(0,), tasks=(0, 1, 2), episodes=2,
                         workers=1, random_row=False, env_config=cfg, seed_set="validation")
        out[name] = sum((c.counts for c in cells), Counter())
    assert out["env_wait_chord"].get("success", 0) < 6
    assert out["env_wait_chord_look"] == Counter(success=6)


def test_junction_features_follow_the_sv_rows_and_the_maps_time_to_box_rule():
    from bimacppo_sim import load_map
    road = load_map("dual_lane_4way")
    H = road.H
    cfg = ObservationConfig(max_sv=3, sv_clip=60.0, sv_frame="ego", pad_value=(60.0, 60.0, 0.0, 0.0),
                            junction=True, tta_cap=8.0)
    assert EnvConfig.load(overrides={"observation": {"junction": True}}).obs_dim == 16 + 4
    ego = np.array([-2.0, -H - 20.0, 5.0, math.pi / 2])             # 20 m south of the box, heading north
    svs = np.array([[H + 12.0, 2.0, 6.0, math.pi],                 # east arm, heading west: 12 m at 6 m/s
                    [-H - 5.0, -2.0, 4.0, math.pi],                # west arm, heading away from the centre
                    ])
    o = observe(cfg, ego, np.array([-40.0, 2.0, math.pi]), svs, road)
    base = observe(dataclasses_replace(cfg, junction=False), ego, np.array([-40.0, 2.0, math.pi]), svs)
    assert o.shape == (20,) and np.array_equal(o[:16], base)          # appended: eq. (18)-(20) unchanged
    assert o[16] == pytest.approx(20.0)                               # the EV's gap to the box
    # SV slots in the rows' order (nearest first): the west SV (heading away) is nearer to the EV
    d_east = math.hypot(H + 14.0, H + 22.0)
    d_west = math.hypot(H + 3.0, H + 18.0)
    assert d_west < d_east
    assert o[17] == pytest.approx(8.0)                                # heading away: the cap
    assert o[18] == pytest.approx(12.0 / 6.0)                         # gap / speed
    assert o[19] == pytest.approx(8.0)                                # empty slot: the cap
    inside = observe(cfg, np.array([0.0, 0.0, 3.0, math.pi / 2]), np.zeros(3),
                     np.array([[1.0, 1.0, 0.0, 0.0]]), road)
    assert inside[16] < 0.0 and inside[17] == 0.0                     # inside the box: 0 s
    with pytest.raises(ValueError, match="road map"):
        observe(cfg, ego, np.zeros(3), svs)
    # a map without a junction: nothing is ever coming
    straight = observe(cfg, ego, np.zeros(3), svs, load_map("three_lane_straight"))
    assert straight[16] == pytest.approx(60.0) and np.all(straight[17:] == 8.0)
    with pytest.raises(ConfigError, match="tta_cap"):
        EnvConfig.from_dict({"observation": {"tta_cap": 0.0}})


def test_lane_features_count_the_same_direction_lanes_beside_the_ev_on_the_planners_map():
    """observation.lanes appends (lanes to the left, lanes to the right) of the EV's lane, by the
    walk A3 decodes with: on the three-lane road 0/2, 1/1, 2/0 from left to right; against the
    lane's direction, inside the junction and on a single-lane arm none; everything before them
    unchanged, and the observation size grows by two."""
    from bimacppo_planner.decision import lanes_beside
    from bimacppo_sim import load_map

    road = load_map("three_lane_straight")
    north = math.pi / 2
    centres = [-road.half_road + (k + 0.5) * road.lane_width for k in range(road.n_lanes)]
    assert [lanes_beside(road, x, 0.0, north) for x in centres] == [(0, 2), (1, 1), (2, 0)]
    assert lanes_beside(road, centres[1] + 1.2, 0.0, north + 0.3) == (1, 1)     # off-centre, turned
    assert lanes_beside(road, centres[1], 0.0, -north) == (0, 0)                # against the lane
    dual = load_map("dual_lane_4way")
    y_arm = -dual.H - 20.0
    inner, outer = 0.5 * dual.lane_width, 1.5 * dual.lane_width
    assert lanes_beside(dual, inner, y_arm, north) == (0, 1)
    assert lanes_beside(dual, outer, y_arm, north) == (1, 0)
    assert lanes_beside(dual, 0.0, 0.0, north) == (0, 0)                        # inside the junction
    assert lanes_beside(load_map("single_lane_4way"), inner, y_arm, north) == (0, 0)
    cfg = ObservationConfig(max_sv=3, sv_clip=60.0, sv_frame="ego", pad_value=(60.0, 60.0, 0.0, 0.0),
                            junction=True, tta_cap=8.0, lanes=True)
    assert EnvConfig.load(overrides={"observation": {"junction": True, "lanes": True}}).obs_dim == 16 + 4 + 2
    assert EnvConfig.load(overrides={"observation": {"lanes": True}}).obs_dim == 16 + 2
    ego = np.array([centres[0], -20.0, 6.0, north])
    svs = np.array([[centres[1], 0.0, 2.0, north]])
    o = observe(cfg, ego, np.array([centres[0], 80.0, north]), svs, road)
    without = observe(dataclasses_replace(cfg, lanes=False), ego, np.array([centres[0], 80.0, north]), svs, road)
    assert o.shape == (22,) and np.array_equal(o[:20], without) and list(o[20:]) == [0.0, 2.0]
    with pytest.raises(ValueError, match="road map"):
        observe(dataclasses_replace(cfg, junction=False), ego, np.zeros(3), svs)


def test_junction_features_carry_the_yield_rules_threat_test():
    """On the states of random drives, the privileged threat test is a function of what the
    junction features show (for the SVs in the watched area): the observation holds the signal
    the threat-entry price is paid on."""
    from bimacppo_sim import Scenario, World, load_map
    from bimacppo_sim.config import DriverConfig
    from bimacppo_sim.drivers import junction_threatened
    road = load_map("dual_lane_4way")
    w, dcfg = World(road), DriverConfig.load()
    cfg = ObservationConfig(max_sv=3, sv_clip=60.0, sv_frame="ego", pad_value=(60.0, 60.0, 0.0, 0.0),
                            junction=True, tta_cap=8.0)
    rng = np.random.default_rng(3)
    seen = Counter()
    for k in range(6):
        w.reset(Scenario(n_sv=3, task=("left", "straight", "right")[k % 3], seed=900 + k))
        for _ in range(150):
            svs = w.sv_states()
            o = observe(cfg, w.ego, w.goal, svs, road)
            order = np.argsort(np.hypot(svs[:, 0] - w.ego[0], svs[:, 1] - w.ego[1]), kind="stable")
            watched = np.array([w.sv_active[i] and math.hypot(*svs[i, :2]) <= dcfg.watch_distance for i in order])
            from_obs = bool(np.any(o[17:][watched] < dcfg.safe_time_gap))
            assert from_obs == junction_threatened(w, dcfg)
            seen[from_obs] += 1
            if w.step(np.array([rng.uniform(-1, 2), rng.uniform(-0.2, 0.2)])).done:
                break
    assert seen[True] > 10 and seen[False] > 10


def test_corridor_on_road_tests_the_centreline_and_both_edges():
    from bimacppo_planner.decision import corridor_on_road
    square = lambda x, y: abs(x) <= 5.0 and abs(y) <= 5.0          # noqa: E731
    assert corridor_on_road(-4.0, 0.0, 4.0, 0.0, 1.0, square)
    assert not corridor_on_road(-4.0, 4.5, 4.0, 4.5, 1.0, square)    # an edge leaves the square
    assert corridor_on_road(-4.0, 4.5, 4.0, 4.5, 0.4, square)
    assert not corridor_on_road(0.0, 0.0, 0.0, 6.0, 0.1, square)     # the far end leaves it
    assert corridor_on_road(1.0, 1.0, 1.0, 1.0, 1.0, square)         # zero length: the point


def test_road_chord_rule_keeps_far_waypoints_for_an_ev_off_the_route_and_folds_at_the_kerb():
    """On the real map: an EV one lane left of its route on the straight approach keeps WP4
    under the road rule (the route rule sends it to WP0, a point beside it); in the right turn
    a waypoint whose straight corridor crosses the kerb is folded back to one whose corridor
    stays on the road."""
    from bimacppo_planner.decision import corridor_on_road
    from bimacppo_sim import Scenario, World, load_map
    road = load_map("dual_lane_4way")
    w = World(road)
    w.reset(Scenario(n_sv=0, task="right", seed=5))
    acfg = EnvConfig.load(REPO_ENV_JUNCTION).action
    assert acfg.chord_rule == "road" and acfg.chord_tol == 1.0
    route_rule = dataclasses_replace(acfg, chord_rule="route")
    route = w.route
    # on the straight approach, one lane to the left of the route
    i = int(np.argmax(route[:, 1] > -30.0))
    x, y = route[i, 0] - road.lane_width, route[i, 1]
    ego = np.array([x, y, 5.0, math.pi / 2])
    tr = WaypointTracker.for_action(route, acfg)
    tr.update(x, y)
    far = tr.candidates()[4]
    got, _ = decode_action([4, 2, 1], tr, acfg, road.lateral_point, ego, road.drivable)
    np.testing.assert_allclose(got[:2], far[:2])
    near, _ = decode_action([4, 2, 1], tr, route_rule, road.lateral_point, ego, road.drivable)
    np.testing.assert_allclose(near[:2], tr.candidates()[0][:2])
    with pytest.raises(ValueError, match="drivable"):
        decode_action([4, 2, 1], tr, acfg, road.lateral_point, ego)
    # along the right turn: every chosen reference is reached on the road, and a fold-back
    # happens only where the next waypoint out would leave it
    folded = 0
    for j in range(len(route) - 6):
        x, y, psi = route[j]
        tr = WaypointTracker.for_action(route, acfg)
        tr.update(x, y)
        ego = np.array([x, y, 5.0, psi])
        got, _ = decode_action([4, 2, 1], tr, acfg, road.lateral_point, ego, road.drivable)
        k = next(k for k in range(5) if np.allclose(tr.candidates()[k][:2], got[:2]))
        if k > 0:
            assert corridor_on_road(x, y, got[0], got[1], 1.0, road.drivable)
        if k < 4:
            nxt = tr.candidates()[k + 1]
            assert not corridor_on_road(x, y, nxt[0], nxt[1], 1.0, road.drivable)
            folded += 1
    assert folded > 0


def test_road_chord_rule_brings_constant_far_waypoint_drivers_through_the_empty_junction():
    """End to end through the env and the NMPC: constant far-waypoint actions, with and without
    lane changes, on the empty road. The route rule leaves the road in some (an EV off its route
    is sent to WP0 beside it), the road rule in none."""
    from bimacppo_common.conventions import TASKS
    from bimacppo_learning.evaluate import evaluate

    class Constant:
        def __init__(self, a):
            self.a = np.array(a, np.int64)

        def act(self, obs):
            return self.a
    fails = {"route": 0, "road": 0}
    for rule in fails:
        cfg = EnvConfig.load(REPO_ENV_JUNCTION, overrides={"action.chord_rule": rule})
        for task, a in (("straight", (4, 3, 2)), ("right", (4, 3, 0)), ("right", (4, 4, 1))):
            c = evaluate(Constant(a), map_id="dual_lane_4way", n_svs=(0,), tasks=(TASKS.index(task),), episodes=3,
                         workers=1, random_row=False, env_config=cfg, seed_set="validation")[0]
            fails[rule] += 3 - c.counts.get("success", 0)
    assert fails["road"] == 0 and fails["route"] >= 3, fails


def test_hold_with_a_deceleration_stops_ahead_along_the_route_at_the_evs_offset():
    lateral = lambda x, y, psi, side: (x - 3.5 * side, y, psi)     # noqa: E731
    hold = ActionConfig(n_waypoints=5, speeds=(0.0, 2.0, 4.0, 6.0, 8.0), lane_change=(-1, 0, 1),
                        decision_every=3, zero_speed="hold", hold_decel=4.0)
    # straight route north along x = 0; the EV 1.5 m to its right at 8 m/s: the stop lies
    # 8^2 / (2 * 4) = 8 m ahead, still 1.5 m to the right, facing north
    tr = WaypointTracker(_straight_route(), 5)
    tr.update(1.5, 10.0)
    for a1 in range(5):
        for a3 in range(3):
            x, changed = decode_action([a1, 0, a3], tr, hold, lateral, np.array([1.5, 10.0, 8.0, 1.4]))
            np.testing.assert_allclose(x, [1.5, 18.0, 0.0, math.pi / 2], atol=1e-9)
            assert not changed
    # standing: the EV's own position, as without a deceleration
    np.testing.assert_allclose(decode_action([2, 0, 1], tr, hold, lateral, np.array([1.5, 10.0, 0.0, 1.4]))[0],
                               [1.5, 10.0, 0.0, math.pi / 2], atol=1e-9)
    # in a turn the stop follows the route's bend over the braking distance
    route = _turning_route()
    tr = WaypointTracker(route, 5)
    tr.update(0.0, -1.0)
    d = 6.0 ** 2 / (2 * 4.0)                                       # 4.5 m: 1 m of straight, 3.5 m of arc
    x, _ = decode_action([0, 0, 1], tr, hold, lateral, np.array([0.0, -1.0, 6.0, math.pi / 2]))
    th = math.pi - (d - 1.0) / 8.0                                  # on the circle around (8, 0)
    assert x[:2] == pytest.approx([8.0 + 8.0 * math.cos(th), 8.0 * math.sin(th)], abs=0.15)
    assert x[3] < math.pi / 2 and x[2] == 0.0
    # past the route's end it stays at the end
    tr = WaypointTracker(_straight_route(), 5)
    tr.update(0.0, 56.0)
    end, _ = decode_action([0, 0, 1], tr, hold, lateral, np.array([0.0, 56.0, 8.0, math.pi / 2]))
    assert end[1] == pytest.approx(57.0)
    with pytest.raises(ConfigError, match="hold_decel"):
        EnvConfig.from_dict({"action": {"hold_decel": 0.0}})
    assert EnvConfig.from_dict({"action": {"zero_speed": "hold"}}).action.hold_decel is None   # older records


def test_a_stop_from_speed_brakes_straight_with_the_stop_ahead_and_swerves_without_it():
    """End to end through the env and the NMPC: at 7-9 m/s on the empty straight approach, a
    held stop at the EV's own position leaves a target behind the car and the NMPC turns towards
    it (up to a U-turn, off the road); the stop ahead at the braking distance brakes straight."""
    turns = {}
    for decel in (None, 4.0):
        cfg = EnvConfig.load(REPO_ENV_JUNCTION, overrides={"action.hold_decel": decel})
        from bimacppo_learning.env import IntersectionEnv
        env = IntersectionEnv(config=cfg)
        worst, crashed = 0.0, 0
        for seed in (101, 102):
            env.reset(options={"n_sv": 0, "task": "straight", "scenario_seed": seed})
            for _ in range(4):
                env.step(np.array([4, 3, 0]))                       # far, 6 m/s, a lane to the left
            psi0 = env.world.ego_tuple()[3]
            assert env.world.ego_tuple()[2] > 7.0
            for _ in range(6):
                _, _, term, trunc, info = env.step(np.array([0, 0, 1]))
                worst = max(worst, abs(env.world.ego_tuple()[3] - psi0))
                if term or trunc:
                    crashed += info["outcome"] == "collision"
                    break
        env.close()
        turns[decel] = (math.degrees(worst), crashed)
    assert turns[None][0] > 60.0 and turns[None][1] >= 1, turns
    assert turns[4.0][0] < 15.0 and turns[4.0][1] == 0, turns


def test_lanes_across_walks_the_carriageway_and_finds_nothing_inside_a_junction():
    from bimacppo_planner.decision import lanes_across
    from bimacppo_sim import load_map
    road = load_map("three_lane_straight")
    x, y, psi = road.lane_point("road_0", 50.0)
    lanes = lanes_across(road.lateral_point, x, y, psi)
    assert sorted(lanes) == [0, 1, 2]
    for n, (lx, ly, lpsi, off) in lanes.items():
        assert off == pytest.approx(-n * road.lane_width) and lx == pytest.approx(x + n * road.lane_width)
    x, y, psi = road.lane_point("road_1", 50.0)
    assert sorted(lanes_across(road.lateral_point, x, y, psi)) == [-1, 0, 1]
    four = load_map("dual_lane_4way")
    assert sorted(lanes_across(four.lateral_point, 0.0, 0.0, math.pi / 2)) == [0]   # the junction's centre


def _three_lane_tracker(acfg):
    from bimacppo_sim import load_map
    road = load_map("three_lane_straight")
    x0, y0, psi = road.lane_point("road_0", 10.0)
    route = np.array([road.lane_point("road_0", s) for s in np.arange(10.0, 120.0, 3.0)])
    tr = WaypointTracker.for_action(route, acfg)
    return road, tr, x0, y0, psi


@pytest.mark.parametrize("rule", ["route", "road"])
def test_lane_changes_count_from_the_chosen_lane_with_lane_change_from_chosen(rule):
    """Route lane 0 (leftmost) of the three-lane road, the EV in it. From the route (the default):
    every decision's A3 counts from the route's lane, so "keep" goes back to it and two rights
    reach lane 1 only. From the chosen lane: a change is remembered, "keep" holds it, two rights
    reach lane 2, a third finds no lane (not a change), a left comes back one lane; a new
    tracker (a new episode) starts on the route's lane."""
    base = EnvConfig.load(REPO_ENV_JUNCTION, overrides={"action.chord_rule": rule}).action
    chosen = dataclasses_replace(base, lane_change_from="chosen")
    keep, right, left = 1, 2, 0
    w = 3.5
    script = [(keep, 0, 0, False), (right, 1, 1, True), (keep, 0, 1, False), (right, 1, 2, True),
              (right, 1, 2, False), (keep, 0, 2, False), (left, 0, 1, True), (left, 0, 0, True),
              (left, 0, 0, False)]
    for acfg, col in ((base, 1), (chosen, 2)):
        road, tr, x0, y0, psi = _three_lane_tracker(acfg)
        ego = np.array([x0, y0 + 20.0, 6.0, psi])
        tr.update(ego[0], ego[1])
        for step in script:
            got, changed = decode_action([4, 3, step[0]], tr, acfg, road.lateral_point, ego, road.drivable)
            assert got[0] == pytest.approx(x0 + step[col] * w), (acfg.lane_change_from, step)
            if acfg is chosen:
                assert changed == step[3] and tr.lane == step[2], step
        if acfg is chosen:
            assert _three_lane_tracker(acfg)[1].lane == 0


def test_a_chosen_lane_returns_to_the_route_where_no_lane_lies_beside_it():
    """Inside the junction no lane lies beside the route: the chosen lane clamps to the route's,
    and stays there after the junction (it is not carried across to the exit arm)."""
    from bimacppo_sim import Scenario, World, load_map
    road = load_map("dual_lane_4way")
    w = World(road)
    w.reset(Scenario(n_sv=0, task="straight", seed=1))
    acfg = dataclasses_replace(EnvConfig.load(REPO_ENV_JUNCTION).action, lane_change_from="chosen")
    route = w.route
    tr = WaypointTracker.for_action(route, acfg)
    tr.lane = 1
    j = int(np.argmin(np.hypot(route[:, 0], route[:, 1])))     # the route point nearest the centre
    x, y, psi = route[j - 2]
    tr.update(x, y)
    got, changed = decode_action([0, 3, 1], tr, acfg, road.lateral_point, np.array([x, y, 6.0, psi]), road.drivable)
    assert tr.lane == 0 and not changed
    np.testing.assert_allclose(got[:2], tr.candidates()[0][:2])


def _three_lane_decode(acfg, ev_x, a3, a1=4):
    from bimacppo_sim import load_map
    road = load_map("three_lane_straight")
    x0, y0, psi = road.lane_point("road_0", 10.0)
    route = np.array([road.lane_point("road_0", s) for s in np.arange(10.0, 120.0, 3.0)])
    tr = WaypointTracker.for_action(route, acfg)
    ego = np.array([ev_x, y0 + 20.0, 6.0, psi])
    tr.update(ego[0], ego[1])
    x_imr, changed = decode_action([a1, 3, a3], tr, acfg, road.lateral_point, ego, road.drivable)
    return x_imr, changed, x0, road.lane_width


@pytest.mark.parametrize("rule", ["route", "road"])
def test_lane_changes_count_from_the_evs_lane_with_lane_change_from_ev(rule):
    """Route lane 0 (leftmost) of the three-lane road. From the route (the default): "keep" is the
    route's lane wherever the EV is and a change reaches one lane beside it. From the EV: "keep"
    is the lane whose centre is nearest the EV, a change one lane further, none beyond the kerb."""
    base = EnvConfig.load(REPO_ENV_JUNCTION, overrides={"action.chord_rule": rule}).action
    ev = dataclasses_replace(base, lane_change_from="ev")
    keep, right, left = 1, 2, 0
    x0 = _three_lane_decode(base, 0.0, keep)[2]
    w = 3.5
    cases = [   # (EV's offset right of the route lane, A3) -> lane reached (route rule, EV rule), EV rule's changed
        (0.0, keep, 0, 0, False), (0.0, right, 1, 1, True), (0.0, left, 0, 0, False),
        (w, keep, 0, 1, False), (w, right, 1, 2, True), (w, left, 0, 0, True),
        (2 * w, keep, 0, 2, False), (2 * w, right, 1, 2, False), (2 * w, left, 0, 1, True),
        (0.45 * w, keep, 0, 0, False), (0.55 * w, keep, 0, 1, False),    # mid-change: the nearer centre
    ]
    for off, a3, lane_route, lane_ev, changed_ev in cases:
        got, _, _, _ = _three_lane_decode(base, x0 + off, a3)
        assert got[0] == pytest.approx(x0 + lane_route * w), (off, a3)
        got, changed, _, _ = _three_lane_decode(ev, x0 + off, a3)
        assert got[0] == pytest.approx(x0 + lane_ev * w) and changed == changed_ev, (off, a3)
    with pytest.raises(ValueError, match="ego"):
        decode_action([4, 3, 1], WaypointTracker.for_action(np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]]), ev),
                      dataclasses_replace(ev, chord_tol=None), lambda *a: None)


def test_two_right_changes_reach_the_far_lane_only_from_the_evs_or_the_chosen_lane():
    """Closed loop through the env and the NMPC on the empty three-lane road, EV starting in the
    leftmost lane: two A3 = right decisions, then "keep" for 6 s, end two lanes over with the
    changes counted from the chosen lane; held right for 6 s, the EV ends one lane over (beside
    the route) with changes counted from the route, and "keep" then goes back to the route's
    lane, two lanes over with changes counted from the EV's lane, and "keep" stays there."""
    from bimacppo_learning.env import IntersectionEnv
    runs = {"route": ((2, 20), (1, 10)), "ev": ((2, 20), (1, 10)), "chosen": ((2, 2), (1, 28))}
    ends = {}
    for frm, script in runs.items():
        env = IntersectionEnv("three_lane_straight", config=EnvConfig.load(
            REPO_ENV_JUNCTION, overrides={"action.lane_change_from": frm}))
        seed = next(s for s in range(100) if (env.reset(options={"n_sv": 0, "task": "straight", "scenario_seed": s})
                                              and env.world.start_lane == "road_0"))
        env.reset(options={"n_sv": 0, "task": "straight", "scenario_seed": seed})
        x0 = env.world._ev[0]
        for a3, decisions in script:
            for _ in range(decisions):
                _, _, term, trunc, _ = env.step(np.array([4, 3, a3]))
                assert not (term or trunc)
            if frm != "chosen":
                ends.setdefault(frm, []).append(round((env.world._ev[0] - x0) / env.road.lane_width, 2))
        if frm == "chosen":
            ends[frm] = [round((env.world._ev[0] - x0) / env.road.lane_width, 2)]
    want = {"route": [1.0, 0.0], "ev": [2.0, 2.0], "chosen": [2.0]}
    assert all(abs(a - b) <= 0.15 for k in want for a, b in zip(ends[k], want[k])), ends


def test_lane_change_commit_holds_a3_until_the_ev_is_near_the_chosen_lanes_centre():
    """Route lane 0 (leftmost) of the three-lane road, changes counted from the chosen lane, the
    commitment at 1 m. With the EV in the chosen lane, a right moves the chosen lane (as without
    the commitment); while the EV is more than 1 m across from the new lane's centre, a left or a
    second right reads "keep" (not a change, the chosen lane stays); once it is within 1 m, A3
    counts again. Off (null, the default): the second decision reverses the change at once.
    Holding only reversals: a change back is held, one onwards to the lane two over counts at
    once. The commitment needs the EV pose."""
    base = dataclasses_replace(EnvConfig.load(REPO_ENV_JUNCTION).action, lane_change_from="chosen")
    commit = dataclasses_replace(base, lane_change_commit=1.0)
    keep, right, left = 1, 2, 0
    w = 3.5
    script = [  # (EV's offset right of the route lane, A3) -> chosen lane, changed; committed, then off
        (0.0, right, (1, True), (1, True)),
        (0.3 * w, left, (1, False), (0, True)),
        (0.6 * w, right, (1, False), (1, True)),
        (0.75 * w, keep, (1, False), (1, False)),
        (w - 0.9, right, (2, True), (2, True)),
        (w, left, (2, False), (1, True)),
    ]
    for acfg, col in ((commit, 2), (base, 3)):
        road, tr, x0, y0, psi = _three_lane_tracker(acfg)
        for step in script:
            ego = np.array([x0 + step[0], y0 + 20.0, 6.0, psi])
            tr.update(ego[0], ego[1])
            got, changed = decode_action([4, 3, step[1]], tr, acfg, road.lateral_point, ego, road.drivable)
            lane, want_changed = step[col]
            assert tr.lane == lane and changed == want_changed, (acfg.lane_change_commit, step)
            assert got[0] == pytest.approx(x0 + lane * w), (acfg.lane_change_commit, step)
    reversals = dataclasses_replace(commit, lane_change_commit_holds="reversals")
    road, tr, x0, y0, psi = _three_lane_tracker(reversals)
    for off, a3, lane, want_changed in ((0.0, right, 1, True), (0.3 * w, left, 1, False), (0.3 * w, right, 2, True),
                                        (0.5 * w, left, 2, False), (2 * w - 0.5, left, 1, True)):
        ego = np.array([x0 + off, y0 + 20.0, 6.0, psi])
        tr.update(ego[0], ego[1])
        got, changed = decode_action([4, 3, a3], tr, reversals, road.lateral_point, ego, road.drivable)
        assert tr.lane == lane and changed == want_changed and got[0] == pytest.approx(x0 + lane * w), (off, a3)
    road, tr, *_ = _three_lane_tracker(commit)
    with pytest.raises(ValueError, match="ego"):
        decode_action([4, 3, right], tr, dataclasses_replace(commit, chord_tol=None), road.lateral_point)


def test_lane_change_commit_is_validated_and_off_by_default():
    assert EnvConfig.load().action.lane_change_commit is None
    chosen = {"action.lane_change_from": "chosen"}
    assert EnvConfig.load(overrides={**chosen, "action.lane_change_commit": 0.8}).action.lane_change_commit == 0.8
    with pytest.raises(ConfigError, match="lane_change_commit"):
        EnvConfig.load(overrides={**chosen, "action.lane_change_commit": 0.0})
    with pytest.raises(ConfigError, match=r"lane_change_commit.*needs lane_change_from: chosen, got 'ev'"):
        EnvConfig.load(overrides={"action.lane_change_from": "ev", "action.lane_change_commit": 1.0})


def test_reach_time_limits_a1_to_the_distance_a2s_speed_covers():
    """Straight route, EV at y = 0.5 so WP0..WP4 lie 2.5 .. 14.5 m ahead. Off (the default): A1
    picks its waypoint whatever A2. With reach_time 1.5 s: the farthest of WP0..WP_A1 no farther
    ahead than 1.5 s at A2's speed, WP0 always; a waypoint three times its lateral offset ahead
    stays allowed, so a lane change is not asked for over a few metres."""
    base = dataclasses_replace(EnvConfig.load().action, speeds=(0.0, 2.0, 4.0, 6.0, 8.0))
    reach = dataclasses_replace(base, reach_time=1.5)
    ego = np.array([0.0, 0.5, 5.0, math.pi / 2])

    def decode(acfg, a1, a2, a3=1, lateral=lambda *a: None):
        tr = WaypointTracker.for_action(_straight_route(), acfg)
        tr.update(0.0, 0.5)
        return decode_action([a1, a2, a3], tr, acfg, lateral, ego)[0]

    for a2, want_y in ((0, 3.0), (1, 3.0), (2, 6.0), (3, 9.0), (4, 12.0)):   # reach 0, 3, 6, 9, 12 m
        assert decode(base, 4, a2)[1] == pytest.approx(15.0)
        got = decode(reach, 4, a2)
        assert got[1] == pytest.approx(want_y) and got[2] == base.speeds[a2], a2
    assert decode(reach, 1, 4)[1] == pytest.approx(6.0)        # a bound, never a push further out
    assert WaypointTracker(_straight_route(), 5).reach_limited(4, 0.0, 0.5, 0.0) == 0

    def left(x, y, psi, side):
        return (x - 3.5, y, psi) if side == -1 else None

    got = decode(reach, 4, 2, a3=0, lateral=left)                   # 4 m/s: 6 m, but 3 x 3.5 m sideways
    assert got[0] == pytest.approx(-3.5) and got[1] == pytest.approx(9.0)
    with pytest.raises(ValueError, match="ego"):
        decode_action([4, 2, 1], WaypointTracker.for_action(_straight_route(), reach), reach, lambda *a: None)
    with pytest.raises(ConfigError, match="reach_time"):
        EnvConfig.load(overrides={"action.reach_time": 0.0})
    assert EnvConfig.load().action.reach_time is None


def test_reach_time_lets_a2_set_the_speed_on_the_empty_road():
    """Closed loop through the env and the NMPC, empty three-lane road, A1 = WP4 held for 7.5 s.
    Without the bound the far waypoint pulls the EV to about 10 m/s whatever A2 asks for; with
    reach_time 1.5 s the EV drives near A2's speed."""
    from bimacppo_learning.env import IntersectionEnv
    end = {}
    for rt in (None, 1.5):
        env = IntersectionEnv("three_lane_straight", config=EnvConfig.load(
            REPO_ENV_JUNCTION, overrides={"action.reach_time": rt}))
        for a2 in (1, 2, 3):
            env.reset(options={"n_sv": 0, "task": "straight", "scenario_seed": 3})
            for _ in range(25):
                _, _, term, trunc, _ = env.step(np.array([4, a2, 1]))
                assert not (term or trunc)
            end[rt, env.cfg.action.speeds[a2]] = env.world._ev[2]
    assert all(end[None, v] > 9.0 for v in (2.0, 4.0, 6.0)), end
    assert all(abs(end[1.5, v] - v) < 1.5 for v in (2.0, 4.0, 6.0)), end


def test_lead_features_give_each_lanes_nearest_sv_ahead_and_behind_on_the_planners_map():
    """observation.leads appends, for the lanes left of the EV, its own and right of it: the
    distance to the nearest same-direction SV ahead in the lane (clip when none), the EV's
    closing speed on it, the distance to the nearest one behind; a missing lane reads zeros.
    SVs are assigned to lanes across the EV's heading, an SV facing the other way is ignored, and
    the features come after every other group."""
    from bimacppo_planner.decision import LEAD_FEATURES, lane_leads
    from bimacppo_sim import load_map

    road = load_map("three_lane_straight")
    north = math.pi / 2
    W = road.lane_width
    left, mid, right = [-road.half_road + (k + 0.5) * W for k in range(road.n_lanes)]
    ego = np.array([mid + 0.3, -20.0, 6.0, north])             # a little right of the middle lane's centre
    svs = np.array([[mid, -8.0, 2.0, north],                    # own lane, 12 m ahead
                    [mid, 10.0, 1.0, north],                    # own lane, farther ahead: not the nearest
                    [left, -19.0, 5.0, north],                  # left lane, beside the EV, 1 m ahead
                    [left, -45.0, 7.0, north],                  # left lane, 25 m behind
                    [right, -5.0, 4.0, -north],                 # right lane, facing the other way: ignored
                    [right, -30.0, 8.0, north]])                # right lane, 10 m behind
    f = lane_leads(road, ego, svs, 60.0)
    assert f.shape == (LEAD_FEATURES,)
    np.testing.assert_allclose(f, [1.0, 1.0, 25.0,  12.0, 4.0, 60.0,  60.0, 0.0, 10.0], atol=1e-9)
    edge = lane_leads(road, np.array([left, -20.0, 6.0, north]), svs[:1], 60.0)
    np.testing.assert_allclose(edge, [0.0, 0.0, 0.0,  60.0, 0.0, 60.0,  12.0, 4.0, 60.0])   # the middle lane is its right
    assert np.allclose(lane_leads(road, ego, svs, 5.0)[[3, 5]], [5.0, 5.0])      # clipped
    dual = load_map("dual_lane_4way")
    inside = lane_leads(dual, np.array([0.0, 0.0, 3.0, north]), np.array([[0.0, 5.0, 1.0, north]]), 60.0)
    np.testing.assert_allclose(inside, [0.0, 0.0, 0.0,  5.0, 2.0, 60.0,  0.0, 0.0, 0.0], atol=1e-9)   # junction: own lane only
    cfg = ObservationConfig(max_sv=3, sv_clip=60.0, sv_frame="ego", pad_value=(60.0, 60.0, 0.0, 0.0),
                            junction=True, tta_cap=8.0, lanes=True, leads=True)
    assert EnvConfig.load(overrides={"observation": {"junction": True, "lanes": True, "leads": True}}).obs_dim \
        == 16 + 4 + 2 + LEAD_FEATURES
    goal = np.array([mid, 80.0, north])
    o = observe(cfg, ego, goal, svs, road)
    without = observe(dataclasses_replace(cfg, leads=False), ego, goal, svs, road)
    assert o.shape == (22 + LEAD_FEATURES,) and np.array_equal(o[:22], without)
    np.testing.assert_allclose(o[22:], f, rtol=1e-6)
    assert np.array_equal(observe(dataclasses_replace(cfg, lanes=False), ego, goal, svs, road)[20:], o[22:])
    with pytest.raises(ValueError, match="road map"):
        observe(dataclasses_replace(cfg, junction=False, lanes=False), ego, goal, svs)
