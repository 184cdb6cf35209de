"""The batched decision step: B episodes in one IntersectionBatch reproduce B single envs.

Parity is the point of the design (batch.py): the Gymnasium env is the batch with one slot, the
training vector env the batch with num_envs slots, so a slot must not feel its neighbours (shared
NMPC call, per-slot warm starts, per-slot resets in the middle of the others' episodes).
"""
import numpy as np
import pytest

from bimacppo_learning.batch import IntersectionBatch
from bimacppo_sim import draw_n_slow
from bimacppo_learning.env import IntersectionEnv
from bimacppo_learning.rollout import make_vector_env, reset_each, reset_one
from bimacppo_learning.vec_env import BatchedVectorEnv, EnvFactory
from bimacppo_planner.decision import EnvConfig

EXT = EnvConfig.from_dict({"observation": {"sv_frame": "ego", "sv_clip": 30.0, "pad_value": [30.0, 30.0, 0.0, 0.0]},
                           "action": {"decision_every": 3}})
OPTS = [{"n_sv": 3, "task": 0}, {"n_sv": 2, "task": "straight"}, {"n_sv": 1, "task": 2}]


def _random_actions(rng, nvec, b):
    # biased towards moving on (speed index >= 2) so that episodes end by success or collision too
    a = np.stack([rng.integers(0, n, size=b) for n in nvec], 1)
    a[:, 1] = np.maximum(a[:, 1], rng.integers(2, nvec[1], size=b))
    return a


def test_batch_reproduces_separate_single_envs_slot_by_slot():
    B = 3
    batch = IntersectionBatch(B, config=EXT)
    envs = [IntersectionEnv(config=EXT) for _ in range(B)]
    ob = np.stack([batch.reset(i, seed=100 + i, options=OPTS[i])[0] for i in range(B)])
    oe = np.stack([envs[i].reset(seed=100 + i, options=OPTS[i])[0] for i in range(B)])
    np.testing.assert_array_equal(ob, oe)
    rng = np.random.default_rng(0)
    outcomes = set()
    ended = 0
    for t in range(240):
        a = _random_actions(rng, EXT.nvec, B)
        o, r, te, tr, inf = batch.step(a)
        for i in range(B):
            o2, r2, te2, tr2, inf2 = envs[i].step(a[i])
            np.testing.assert_allclose(o[i], o2, rtol=0, atol=1e-9)
            assert r[i] == pytest.approx(r2, abs=1e-12)
            assert (te[i], tr[i]) == (te2, tr2)
            np.testing.assert_array_equal(batch.worlds[i].ego, envs[i].world.ego)
            if te[i] or tr[i]:
                assert inf[i]["outcome"] == inf2["outcome"]
                assert inf[i]["episode_return"] == pytest.approx(inf2["episode_return"])
                outcomes.add(inf[i]["outcome"])
                ended += 1
                s = 1000 + 10 * t + i       # a slot restarts while its neighbours keep driving
                batch.reset(i, seed=s, options=OPTS[i])
                envs[i].reset(seed=s, options=OPTS[i])
    assert ended >= 6 and len(outcomes) >= 2, (ended, outcomes)


def test_a_slot_must_be_reset_before_it_steps_again():
    batch = IntersectionBatch(2, config=EXT)
    with pytest.raises(RuntimeError, match=r"slot\(s\) \[0, 1\] need reset"):
        batch.step(np.zeros((2, 3), np.int64))
    batch.reset(0, seed=1, options=OPTS[0])
    with pytest.raises(RuntimeError, match=r"\[1\]"):
        batch.step(np.zeros((2, 3), np.int64))
    batch.reset(1, seed=2, options=OPTS[1])
    with pytest.raises(ValueError, match="shape"):
        batch.step(np.zeros((3, 3), np.int64))
    with pytest.raises(ValueError, match="unknown reset option"):
        batch.reset(0, seed=1, options={"n_svs": 2})
    with pytest.raises(ValueError, match="num_envs"):
        IntersectionBatch(0)


def test_vector_env_resets_only_masked_slots_and_reports_finished_episodes():
    venv = make_vector_env(EnvFactory(env_config=EXT), 3, "batched")
    assert isinstance(venv, BatchedVectorEnv)
    obs = reset_each(venv, [5, 6, 7], OPTS)
    assert obs.shape == (3, EXT.obs_dim)
    before = [w.scenario for w in venv.batch.worlds]
    o1, _ = reset_one(venv, 1, 42, {"n_sv": 0, "task": 1})
    after = [w.scenario for w in venv.batch.worlds]
    assert after[0] is before[0] and after[2] is before[2] and after[1].n_sv == 0
    np.testing.assert_array_equal(o1, venv.batch.observe(1))
    rng = np.random.default_rng(3)
    for _ in range(400):
        o, r, te, tr, infos = venv.step(_random_actions(rng, EXT.nvec, 3))
        done = te | tr
        if done.any():
            assert set(np.nonzero(infos["_outcome"])[0]) == set(np.nonzero(done)[0])
            for i in np.nonzero(done)[0]:
                assert infos["outcome"][i] in ("success", "collision", "timeout")
                assert infos["episode_ticks"][i] > 0
            break
    else:
        pytest.fail("no episode ended in 400 decisions")
    venv.close()


def test_batched_mode_needs_a_factory_with_make_batch():
    with pytest.raises(ValueError, match="make_batch"):
        make_vector_env(lambda: IntersectionEnv(config=EXT), 2, "batched")


def test_single_task_map_folds_tasks_and_slow_svs_follow_the_scenario_seed():
    batch = IntersectionBatch(1, map_id="three_lane_straight", config=EXT, slow_svs=2)
    for seed in range(6):
        batch.reset(0, seed=seed, options={"n_sv": 3, "task": "left"})
        sc = batch.scenarios[0]
        assert sc.task == "straight"
        assert sc.n_slow == draw_n_slow(sc.seed, 3, 2)
        assert sum(sv.slow for sv in batch.worlds[0].svs) == sc.n_slow


def test_worker_processes_give_the_in_process_trajectories_and_report_worker_errors():
    one = BatchedVectorEnv(3, config=EXT)
    two = BatchedVectorEnv(3, workers=2, config=EXT)
    try:
        o1 = reset_each(one, [11, 12, 13], OPTS)
        o2 = reset_each(two, [11, 12, 13], OPTS)
        np.testing.assert_array_equal(o1, o2)
        rng = np.random.default_rng(5)
        for t in range(60):
            a = _random_actions(rng, EXT.nvec, 3)
            r1, r2 = one.step(a), two.step(a)
            np.testing.assert_array_equal(r1[0], r2[0])
            np.testing.assert_array_equal(r1[1], r2[1])
            for i in np.nonzero(r1[2] | r1[3])[0]:
                assert r2[4]["outcome"][i] == r1[4]["outcome"][i]
                reset_one(one, int(i), 500 + t, OPTS[i])
                reset_one(two, int(i), 500 + t, OPTS[i])
        # the NMPC's work is counted per block and summed over the processes; a tick solves every
        # slot of its block, so one block of 3 solves a finished slot until the others finish too,
        # and two blocks solve no more than that
        s1, s2 = one.mpc_stats(), two.mpc_stats()
        assert s1["problems"] % 3 == 0 and 60 * 3 <= s2["problems"] <= s1["problems"] <= 60 * 3 * EXT.action.decision_every
        for st in (s1, s2):
            assert st["iterations"] >= st["problems"] > st["second_starts"] >= 0 and st["seconds"] > 0.0
            # CPU time is counted too (every thread of the solve); a solve keeps a core busy, so it is
            # no less than a fraction of the wall time it took
            assert st["cpu_seconds"] > 0.2 * st["seconds"]
        with pytest.raises(RuntimeError, match="batched env worker: ValueError: unknown reset option"):
            reset_one(two, 2, 1, {"bogus": 1})
    finally:
        one.close()
        two.close()
    with pytest.raises(ValueError, match="workers"):
        BatchedVectorEnv(2, workers=3, config=EXT)


def test_threat_entry_shaping_changes_returns_only_and_only_on_threatened_entries():
    """The same scenarios and actions with and without the shaping term: the trajectories are the
    same, and an episode's return is lower by exactly |threat_entry| iff it entered a threatened
    junction. A timeout is a truncation in truncate mode and a termination in terminal mode."""
    shaped = EnvConfig.from_dict({**EXT.to_dict(), "reward": {**EXT.to_dict()["reward"], "threat_entry": -7.0,
                                                               "timeout_mode": "truncate"}})
    plain = EnvConfig.from_dict({**EXT.to_dict(), "reward": {**EXT.to_dict()["reward"], "timeout_mode": "terminal"}})
    go = np.array([[4, 4, 1]])          # farthest waypoint at 8 m/s: never yields
    flags = []
    for k in range(8):
        ends = []
        for cfg in (shaped, plain):
            b = IntersectionBatch(1, config=cfg)
            b.reset(0, seed=k, options={"n_sv": 3 * (k % 2), "task": k % 3})
            while True:
                _, _, te, tr, inf = b.step(go)
                if te[0] or tr[0]:
                    ends.append((inf[0], bool(te[0]), bool(tr[0]), b.worlds[0].ego.copy()))
                    break
        (i1, te1, tr1, ego1), (i2, te2, tr2, ego2) = ends
        np.testing.assert_array_equal(ego1, ego2)
        assert i1["outcome"] == i2["outcome"] and i1["threat_entry"] == i2["threat_entry"]
        flags.append(i1["threat_entry"])
        if i1["outcome"] == "timeout":
            assert (te1, tr1, te2, tr2) == (False, True, True, False)
        else:
            assert te1 and te2 and not tr1 and not tr2
            assert i1["episode_return"] - i2["episode_return"] == pytest.approx(-7.0 * i1["threat_entry"])
    assert any(flags) and not all(flags), flags      # both kinds of episode occurred



def _run_logging_threat_test(monkeypatch, cfg, action, seed, task, max_decisions=1000, n_sv=3):
    """One episode with ``n_sv`` SVs (at most ``max_decisions``) of a constant ``action``, logging at every
    call of the yield rule's threat test (the start of each tick before the junction) the EV's
    speed, its distance to the box and the verdict. Returns (return, log, final ego, crossed)."""
    import bimacppo_learning.batch as batch_mod

    real_test, log = batch_mod.junction_threatened, []

    def test(world, tcfg):
        out = real_test(world, tcfg)
        log.append([world.ego_tuple()[2], batch_mod.junction_distance(world), out])
        return out

    monkeypatch.setattr(batch_mod, "junction_threatened", test)
    b = IntersectionBatch(1, config=cfg)
    b.reset(0, seed=seed, options={"n_sv": n_sv, "task": task})
    for _ in range(max_decisions):
        _, _, te, tr, _ = b.step(action)
        if te[0] or tr[0]:
            break
    monkeypatch.setattr(batch_mod, "junction_threatened", real_test)
    return b.returns[0], np.array(log, float), b.worlds[0].ego_tuple(), bool(b.crossed[0])


def test_idle_clear_shaping_prices_standing_only_while_the_junction_is_clear(monkeypatch):
    """The same scenarios and actions with and without the idle-clear term: the trajectories are
    the same, and the return is lower by exactly |idle_clear| / decision_every per tick that began
    with the EV slower than idle_speed while the yield rule's test was false (or the junction was
    passed). A stop-at-WP0 policy comes to a stand and stays, so it stands both while threatened
    and while clear."""
    base = EXT.to_dict()
    price = -0.3
    shaped = EnvConfig.from_dict({**base, "reward": {**base["reward"], "idle_clear": price, "idle_speed": 1.0}})
    plain = EnvConfig.from_dict(base)
    every = shaped.action.decision_every
    stop = np.array([[0, 0, 1]])        # nearest waypoint at 0 m/s
    kinds = {"clear": 0, "threatened": 0}
    for k in range(4):
        (r1, log1, ego1, crossed), (r2, log2, ego2, _) = [
            _run_logging_threat_test(monkeypatch, cfg, stop, k, k % 3, max_decisions=60) for cfg in (shaped, plain)]
        np.testing.assert_array_equal(ego1, ego2)
        np.testing.assert_array_equal(log1, log2)
        assert not crossed                            # the test sees every tick before the junction
        standing = log1[:, 0] < 1.0
        idle_clear = int(np.sum(standing & (log1[:, 2] == 0.0)))
        kinds["clear"] += idle_clear
        kinds["threatened"] += int(np.sum(standing & (log1[:, 2] == 1.0)))
        assert r1 - r2 == pytest.approx(price / every * idle_clear, abs=1e-9)
    assert kinds["clear"] > 0 and kinds["threatened"] > 0, kinds


def test_graded_idle_clear_prices_each_clear_tick_by_its_speed_shortfall(monkeypatch):
    """With ``go_speed`` set, a clear tick pays idle_clear * (1 - v / go_speed) (nothing at or
    above go_speed), a threatened tick nothing: the return differs from the unshaped run's by
    exactly that sum, the trajectories not at all. A creep at 2 m/s (WP0) pays a share between
    0 and 1, which the stand test (go_speed 0) would not price at all."""
    base = EXT.to_dict()
    price, go = -0.3, 4.0
    graded = EnvConfig.from_dict({**base, "reward": {**base["reward"], "idle_clear": price, "go_speed": go}})
    plain = EnvConfig.from_dict(base)
    every = graded.action.decision_every
    creep = np.array([[0, 1, 1]])       # nearest waypoint at 2 m/s
    partial, threatened = 0, 0
    for k in range(4):
        (r1, log1, ego1, crossed), (r2, log2, ego2, _) = [
            _run_logging_threat_test(monkeypatch, cfg, creep, k, k % 3, max_decisions=20, n_sv=3 * (k % 2))
            for cfg in (graded, plain)]
        np.testing.assert_array_equal(ego1, ego2)
        assert not crossed
        share = np.clip(1.0 - log1[:, 0] / go, 0.0, 1.0) * (log1[:, 2] == 0.0)
        partial += int(np.sum((share > 0.05) & (share < 0.95)))
        threatened += int(np.sum(log1[:, 2] == 1.0))
        assert r1 - r2 == pytest.approx(price / every * float(np.sum(share)), abs=1e-9)
    assert partial > 0 and threatened > 0


def test_threat_speed_shaping_prices_only_threatened_approaches_too_fast_to_stop(monkeypatch):
    """The same scenarios and actions with and without the threat-speed term: the trajectories are
    the same, and the return is lower by exactly |threat_speed| / decision_every per tick that
    began with the junction threatened, the EV outside the box, faster than idle_speed and unable
    to stop before the box at the yield rule's braking deceleration (v^2 > 2 b d). A policy that
    drives at 8 m/s towards the junction meets ticks of both kinds (too fast and not yet)."""
    from bimacppo_sim.config import DriverConfig

    decel = DriverConfig.load().stop_decel
    base = EXT.to_dict()
    price = -0.4
    shaped = EnvConfig.from_dict({**base, "reward": {**base["reward"], "threat_speed": price, "idle_speed": 1.0}})
    plain = EnvConfig.from_dict(base)
    every = shaped.action.decision_every
    go = np.array([[4, 4, 1]])          # farthest waypoint at 8 m/s: never yields
    kinds = {"priced": 0, "threatened_but_can_stop": 0}
    for k in range(6):
        (r1, log1, ego1, _), (r2, log2, ego2, _) = [
            _run_logging_threat_test(monkeypatch, cfg, go, k, k % 3) for cfg in (shaped, plain)]
        np.testing.assert_array_equal(ego1, ego2)
        np.testing.assert_array_equal(log1, log2)
        v, d, threat = log1[:, 0], log1[:, 1], log1[:, 2] == 1.0
        too_fast = (v > 1.0) & (v ** 2 > 2.0 * decel * np.maximum(d, 0.0))
        priced = int(np.sum(threat & too_fast))
        kinds["priced"] += priced
        kinds["threatened_but_can_stop"] += int(np.sum(threat & ~too_fast))
        assert r1 - r2 == pytest.approx(price / every * priced, abs=1e-9)
    assert kinds["priced"] > 0 and kinds["threatened_but_can_stop"] > 0, kinds


def _overtaking_pair(monkeypatch, name, configs, seed, actions):
    """Run one overtaking scenario (seed, two slow SVs) under each of ``configs`` with the same
    ``actions(t)`` per decision, recording every call's result of batch.``name`` (a privileged
    test the shaping reads): (return, final EV state, the recorded results) per config."""
    import bimacppo_learning.batch as batch_mod

    real = getattr(batch_mod, name)
    runs = []
    for cfg in configs:
        log = []

        def recorded(*args):
            out = real(*args)
            log.append(out)
            return out
        monkeypatch.setattr(batch_mod, name, recorded)
        b = IntersectionBatch(1, map_id="three_lane_straight", config=cfg, slow_svs=2)
        b.reset(0, seed=seed, options={"n_sv": 3, "task": "straight", "n_slow": 2})
        for t in range(60):
            _, _, te, tr, _ = b.step(np.array([actions(t)]))
            if te[0] or tr[0]:
                break
        runs.append((b.returns[0], b.worlds[0].ego_tuple(), list(log)))
    monkeypatch.setattr(batch_mod, name, real)
    return runs


def test_headway_shaping_prices_the_ticks_closing_on_the_lead_too_fast_to_stop(monkeypatch):
    """The same overtaking scenarios and actions with and without the headway term: the
    trajectories are the same, and the return is lower by exactly |headway| / decision_every per
    tick that began with ``closing_on_lead`` true. Driving at 8 m/s in the lane meets both kinds
    of tick (closing too fast on a slow SV ahead, and not yet)."""
    base = EXT.to_dict()
    price = -0.5
    shaped = EnvConfig.from_dict({**base, "reward": {**base["reward"], "headway": price}})
    plain = EnvConfig.from_dict(base)
    every = shaped.action.decision_every
    kinds = {"priced": 0, "not": 0}
    for k in range(4):
        (r1, ego1, log1), (r2, ego2, _) = _overtaking_pair(monkeypatch, "closing_on_lead", (shaped, plain), k,
                                                           lambda t: [4, 4, 1])
        assert ego1 == ego2
        priced = int(np.sum(log1))
        kinds["priced"] += priced
        kinds["not"] += len(log1) - priced
        assert r1 - r2 == pytest.approx(price / every * priced, abs=1e-9)
    assert kinds["priced"] > 0 and kinds["not"] > 0, kinds


def test_idle_queue_gap_waives_the_idle_price_on_the_ticks_queued_behind_a_lead(monkeypatch):
    """The same overtaking scenarios and actions with the idle price, with and without
    ``idle_queue_gap``: the trajectories are the same, and the return with the gap is higher by
    exactly the price of the ticks that began queued behind a lead (``queued_behind_lead``),
    each ``|idle_clear| * idle_share(v) / decision_every``. Driving at A2 = 4 m/s in the lane, below
    the price's go speed, meets both kinds of tick (queued behind a slow SV, and not yet)."""
    import bimacppo_learning.batch as batch_mod
    from bimacppo_planner.decision import idle_share

    base = EXT.to_dict()
    price, gap = -0.3, 20.0
    reward = {**base["reward"], "idle_clear": price, "go_speed": 8.0}
    plain = EnvConfig.from_dict({**base, "reward": reward})
    waived = EnvConfig.from_dict({**base, "reward": {**reward, "idle_queue_gap": gap}})
    every = waived.action.decision_every
    real = batch_mod.queued_behind_lead
    kinds = {"queued": 0, "not": 0}
    for k in range(4):
        out = []
        for cfg in (waived, plain):
            log = []

            def recorded(world, g):
                q = real(world, g)
                log.append((q, world.ego_tuple()[2]))
                return q
            monkeypatch.setattr(batch_mod, "queued_behind_lead", recorded)
            b = IntersectionBatch(1, map_id="three_lane_straight", config=cfg, slow_svs=2)
            b.reset(0, seed=k, options={"n_sv": 3, "task": "straight", "n_slow": 2})
            for _ in range(60):
                _, _, te, tr, _ = b.step(np.array([[4, 2, 1]]))
                if te[0] or tr[0]:
                    break
            out.append((b.returns[0], b.worlds[0].ego_tuple(), log))
        (r1, ego1, log1), (r2, ego2, log2) = out
        assert ego1 == ego2
        assert log2 == []                       # without the gap the test is never asked
        waived_price = sum(-price * idle_share(waived.reward, v) / every for q, v in log1 if q)
        kinds["queued"] += sum(1 for q, v in log1 if q and idle_share(waived.reward, v) > 0)
        kinds["not"] += sum(1 for q, _ in log1 if not q)
        assert r1 - r2 == pytest.approx(waived_price, abs=1e-9)
    monkeypatch.setattr(batch_mod, "queued_behind_lead", real)
    assert kinds["queued"] > 0 and kinds["not"] > 0, kinds


def test_free_lane_term_pays_the_change_in_lanes_to_the_free_lane(monkeypatch):
    """The same overtaking scenarios and actions (a right change held, then "keep") with and
    without the lane-progress term: the trajectories are the same, and the return differs by
    free_lane times the sum over decisions of the change in ``lanes_to_free_lane`` (None at
    either end pays nothing); among the scenarios some decisions move towards the free lane.
    The count is taken at the reset and after every decision, each one the next decision's start."""
    base = EXT.to_dict()
    price = -2.0
    overtake = {"sv_clip": 60.0, "pad_value": [60.0, 60.0, 0.0, 0.0]}
    shaped = EnvConfig.from_dict({**base, "observation": {**base["observation"], **overtake},
                                  "action": {**base["action"], "lane_change_from": "ev"},
                                  "reward": {**base["reward"], "go_speed": 4.0, "free_lane": price}})
    plain = EnvConfig.from_dict({**base, "observation": {**base["observation"], **overtake},
                                 "action": {**base["action"], "lane_change_from": "ev"},
                                 "reward": {**base["reward"], "go_speed": 4.0}})
    moved = 0
    for k in range(6):
        (r1, ego1, log1), (r2, ego2, log2) = _overtaking_pair(monkeypatch, "lanes_to_free_lane", (shaped, plain), k,
                                                              lambda t: [4, 3, 2 if t < 15 else 1])
        assert ego1 == ego2 and log2 == []
        pairs = list(zip(log1[:-1], log1[1:]))            # (before, after) per decision
        want = sum(price * (a - b0) for b0, a in pairs if a is not None and b0 is not None)
        moved += sum(1 for b0, a in pairs if a is not None and b0 is not None and a < b0)
        assert r1 - r2 == pytest.approx(want, abs=1e-9)
    assert moved > 0
