"""Checkpoints: round trip, corrupt/truncated/foreign/mis-shaped files, resume, policy export."""
import json
import pathlib

import numpy as np
import pytest
import torch

from bimacppo_learning.checkpoint import (CheckpointError, Policy, export_policy, list_checkpoints,
                                         load_checkpoint, save_checkpoint)
from bimacppo_learning.ppo import PPO
from bimacppo_learning.ppo_config import PPOConfig, load_config
from toy_env import ToyIntersectionEnv, ToyScheduler
from bimacppo_learning.trainer import Trainer, load_agent

NVEC = (5, 5, 3)


def cfg(**train):
    base = {"rollout_steps": 16, "vector": "sync", "num_envs": 2, "batch_workers": 1,
            "tensorboard": False, "progress_bar": False,
            "checkpoint_every": 20, "keep_checkpoints": 10}
    base.update(train)
    return load_config(ppo={"minibatch_size": 32, "epochs": 2}, train=base)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    p, t = cfg()
    tr = Trainer(ToyIntersectionEnv, ToyScheduler(seed=0), d, p, t)
    tr.train(episodes=60)
    return tr, d


def history(d):
    return [json.loads(x) for x in (pathlib.Path(d) / "history.jsonl").read_text().splitlines()]


def test_checkpoint_round_trip_restores_everything(trained):
    tr, d = trained
    path = tr.last_checkpoint
    assert path.name == "ckpt_ep00000060.pt"
    ck = load_checkpoint(path)
    assert ck["counters"]["episodes"] == 60
    agent = load_agent(path)
    obs = np.random.default_rng(0).normal(size=(5, agent.obs_dim)).astype(np.float32)
    for a, b in ((agent.actor, tr.agent.actor), (agent.critic, tr.agent.critic)):
        for (k1, v1), (k2, v2) in zip(a.state_dict().items(), b.state_dict().items()):
            assert k1 == k2 and torch.equal(v1, v2)
    np.testing.assert_array_equal(agent.obs_rms.mean, tr.agent.obs_rms.mean)
    np.testing.assert_array_equal(agent.normalize_obs(obs), tr.agent.normalize_obs(obs))
    assert agent.actor_opt.state_dict()["state"].keys() == tr.agent.actor_opt.state_dict()["state"].keys()
    assert json.loads(ck["scheduler_state"]) == json.loads(json.dumps(tr.scheduler.state_dict()))
    # the same sampling generator state -> the same future actions
    np.testing.assert_array_equal(agent.act(agent.normalize_obs(obs))[0],
                                  load_agent(path).act(agent.normalize_obs(obs))[0])
    # only weights_only-safe content: a plain weights_only load works
    torch.load(path, weights_only=True)


def test_periodic_checkpoints_are_written_and_pruned(tmp_path):
    p, t = cfg(checkpoint_every=10, keep_checkpoints=2)
    Trainer(ToyIntersectionEnv, ToyScheduler(), tmp_path, p, t).train(episodes=50)
    cks = list_checkpoints(tmp_path / "checkpoints")
    assert len(cks) == 2 and cks[-1].name == "ckpt_ep00000050.pt"
    assert not list((tmp_path / "checkpoints").glob("*.tmp"))


@pytest.mark.parametrize("damage, match", [
    (lambda p: p.write_bytes(b""), "empty"),
    (lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]), "corrupt or truncated"),
    (lambda p: p.write_bytes(b"\x00garbage" * 100), "corrupt or truncated"),
    (lambda p: p.unlink(), "no such file"),
    (lambda p: torch.save({"hello": 1}, p), "format"),
    (lambda p: torch.save([1, 2, 3], p), "expected a dict"),
])
def test_damaged_checkpoint_raises_checkpoint_error_naming_file(trained, tmp_path, damage, match):
    src = trained[0].last_checkpoint
    dst = tmp_path / "ck.pt"
    dst.write_bytes(src.read_bytes())
    damage(dst)
    with pytest.raises(CheckpointError, match=match) as ei:
        load_checkpoint(dst)
    assert str(dst) in str(ei.value) and ei.value.path == str(dst)


def test_checkpoint_with_unsafe_pickle_is_refused(tmp_path):
    import datetime
    f = tmp_path / "evil.pt"    # any non-allow-listed global must be refused by weights_only
    torch.save({"format": "bimacppo-ppo-checkpoint", "obj": datetime.date(2024, 1, 1)}, f)
    with pytest.raises(CheckpointError, match="corrupt or truncated|Unpickl|weights"):
        load_checkpoint(f)


def test_wrong_shape_checkpoint_is_reported(trained, tmp_path):
    ck = load_checkpoint(trained[0].last_checkpoint)
    ck["agent"]["actor"]["2.weight"] = torch.zeros(64, 256)
    bad = tmp_path / "shape.pt"
    save_checkpoint(bad, ck)
    with pytest.raises(CheckpointError, match=r"actor\.2\.weight.*shape \(64, 256\)") as ei:
        load_agent(bad)
    assert str(bad) in str(ei.value)
    # an agent for another observation size does not accept the file either
    ck2 = load_checkpoint(trained[0].last_checkpoint)
    other = PPO(7, NVEC, PPOConfig(minibatch_size=32, epochs=2))
    from bimacppo_learning.checkpoint import restore_agent
    with pytest.raises(CheckpointError, match="obs_dim"):
        restore_agent(other, ck2["agent"], trained[0].last_checkpoint)


def test_resume_after_kill_continues_counter_and_scheduler(tmp_path):
    p, t = cfg(checkpoint_every=20)

    class Killed(Exception):
        pass

    def kill_at_50(rec):
        if rec["episode"] == 50:
            raise Killed

    sched = ToyScheduler(seed=5)
    with pytest.raises(Killed):
        Trainer(ToyIntersectionEnv, sched, tmp_path, p, t, on_episode=kill_at_50).train(episodes=100)
    assert len(history(tmp_path)) == 50
    last = list_checkpoints(tmp_path / "checkpoints")[-1]
    saved = load_checkpoint(last)
    n0 = saved["counters"]["episodes"]
    assert 40 <= n0 < 50                      # at most one interval (+ one rollout) is lost
    with pytest.raises(ValueError, match="resume=True"):
        Trainer(ToyIntersectionEnv, ToyScheduler(), tmp_path, p, t).train(episodes=100)

    sched2 = ToyScheduler(seed=999)          # state must come from the checkpoint, not the seed
    seen = []
    tr = Trainer(ToyIntersectionEnv, sched2, tmp_path, p, t, on_episode=seen.append)
    res = tr.train(episodes=100, resume=True)
    assert seen[0]["episode"] == n0 + 1 and res.episodes == 100
    recs = history(tmp_path)
    assert [r["episode"] for r in recs] == list(range(1, 101))        # no duplicates, no gaps
    counts_at_ckpt = np.array(json.loads(saved["scheduler_state"])["counts"])
    assert counts_at_ckpt.sum() == n0
    assert sched2.counts.sum() == 100 and np.all(sched2.counts >= counts_at_ckpt)
    assert recs[n0]["env_steps"] > saved["counters"]["env_steps"]
    # the clock continues across the resume: wall_s never drops, so the last record is the run's time
    walls = [r["wall_s"] for r in recs]
    assert walls == sorted(walls) and walls[n0] >= walls[n0 - 1]
    # resuming a finished run is a no-op
    res2 = Trainer(ToyIntersectionEnv, ToyScheduler(), tmp_path, p, t).train(episodes=100, resume=True)
    assert res2.episodes == 100 and len(history(tmp_path)) == 100


def test_resume_with_a_different_ppo_config_is_refused(trained, tmp_path):
    _, d = trained
    p, t = load_config(ppo={"minibatch_size": 32, "epochs": 3}, train=cfg()[1].__dict__)
    with pytest.raises(CheckpointError, match="epochs"):
        Trainer(ToyIntersectionEnv, ToyScheduler(), d, p, t).train(episodes=80, resume=True)


def test_policy_export_is_small_and_acts_like_the_agent(trained, tmp_path):
    tr, d = trained
    path = export_policy(tr.agent, tmp_path / "policy.pt", meta={"map": "toy"})
    full = tr.last_checkpoint.stat().st_size
    assert path.stat().st_size < full / 2
    pol = Policy.load(path)
    assert pol.obs_dim == tr.agent.obs_dim and pol.nvec == NVEC and pol.meta == {"map": "toy"}
    assert len(pol.config_hash) == 16
    rng = np.random.default_rng(0)
    for _ in range(50):
        obs = rng.normal(size=tr.agent.obs_dim).astype(np.float32) * 2
        a = pol.act(obs, deterministic=True)
        assert a.dtype == np.int64 and a.shape == (3,)
        ref = tr.agent.act(tr.agent.normalize_obs(obs[None]), deterministic=True)[0][0]
        np.testing.assert_array_equal(a, ref)
        s = pol.act(obs, deterministic=False, rng=rng)
        assert all(0 <= s[k] < NVEC[k] for k in range(3))
    with pytest.raises(ValueError, match="shape"):
        pol.act(np.zeros(3))
    with pytest.raises(ValueError, match="NaN"):
        pol.act(np.full(tr.agent.obs_dim, np.nan))
    # the trainer exports one at the end of training too
    assert Policy.load(d / "policy.pt").meta["episodes"] == 60


def test_damaged_policy_file_raises(trained, tmp_path):
    tr, _ = trained
    path = export_policy(tr.agent, tmp_path / "p.pt")
    blob = torch.load(path, weights_only=True)
    blob["actor"]["0.weight"] = torch.zeros(3, 3)
    torch.save(blob, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match=r"bad\.pt.*0\.weight"):
        Policy.load(tmp_path / "bad.pt")
    (tmp_path / "trunc.pt").write_bytes(path.read_bytes()[:100])
    with pytest.raises(CheckpointError, match="trunc.pt"):
        Policy.load(tmp_path / "trunc.pt")
    blob["format"] = "someone-elses-format"
    torch.save(blob, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="foreign.pt.*format"):
        Policy.load(tmp_path / "foreign.pt")
    # a full training checkpoint carries the actor: it loads and acts like the export
    from_ckpt, exported = Policy.load(tr.last_checkpoint), Policy.load(path)
    obs = np.linspace(-1.0, 1.0, exported.obs_dim)
    assert np.array_equal(from_ckpt.act(obs), exported.act(obs))


@pytest.mark.parametrize("where", ["actor", "obs_rms", "critic"])
def test_a_non_finite_weight_is_a_corrupt_file_not_a_silent_policy(trained, tmp_path, where, capsys):
    """A NaN or inf in the actor or the normaliser would make every argmax 0 without an error:
    the policy export, the training checkpoint (--resume, --init-policy, evaluation) and
    bimacppo-evaluate refuse it, naming the tensor; a NaN critic spoils a checkpoint too."""
    from bimacppo_learning.cli import evaluate_main

    tr, _ = trained
    blob = torch.load(tr.last_checkpoint, weights_only=True)
    if where == "obs_rms":
        blob["agent"]["obs_rms"]["var"][1] = float("inf")
        name = r"obs_rms\.var"
    else:
        blob["agent"][where]["2.bias"][0] = float("nan")
        name = rf"{where}\.2\.bias holds 1 non-finite"
    torch.save(blob, tmp_path / "ckpt.pt")
    with pytest.raises(CheckpointError, match=rf"ckpt\.pt: {name}"):
        load_checkpoint(tmp_path / "ckpt.pt")
    if where == "critic":
        Policy.load(tmp_path / "ckpt.pt")     # the actor alone is sound: a policy can be taken out of it
        return
    with pytest.raises(CheckpointError, match=name):
        Policy.load(tmp_path / "ckpt.pt")
    export = torch.load(export_policy(tr.agent, tmp_path / "p.pt"), weights_only=True)
    if where == "obs_rms":
        export["obs_rms"]["var"][1] = float("inf")
    else:
        export["actor"]["2.bias"][0] = float("nan")
    torch.save(export, tmp_path / "nan.pt")
    with pytest.raises(CheckpointError, match=rf"nan\.pt: {name}"):
        Policy.load(tmp_path / "nan.pt")
    assert evaluate_main([str(tmp_path / "nan.pt"), "--episodes", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nan.pt" in err[0] and "non-finite" in err[0]


@pytest.mark.parametrize("key, value, match", [
    ("var", -1.0, "obs_rms.var holds negative variances"),
    ("clip", float("nan"), "obs_rms.clip holds 1 non-finite"),
    ("clip", 0.0, r"obs_rms.clip = 0.0 must be > 0"),
    ("eps", -1e-8, r"obs_rms.eps = -1e-08 must be >= 0"),
    ("count", -3.0, r"obs_rms.count = -3.0 must be >= 0"),
    ("mean", "zeros", "obs_rms.mean is a str, not numbers"),
])
def test_a_normaliser_that_cannot_normalise_is_a_corrupt_file(trained, tmp_path, key, value, match):
    """A negative variance or a NaN or zero clip would turn every observation into NaN (or 0)
    and every action into argmax 0 without an error: export and checkpoint are both refused."""
    tr, _ = trained
    export = torch.load(export_policy(tr.agent, tmp_path / "p.pt"), weights_only=True)
    blob = torch.load(tr.last_checkpoint, weights_only=True)
    for rms in (export["obs_rms"], blob["agent"]["obs_rms"]):
        if key == "var":
            rms["var"][0] = value
        else:
            rms[key] = value
    torch.save(export, tmp_path / "bad_export.pt")
    torch.save(blob, tmp_path / "bad_ckpt.pt")
    with pytest.raises(CheckpointError, match=rf"bad_export\.pt: {match}"):
        Policy.load(tmp_path / "bad_export.pt")
    with pytest.raises(CheckpointError, match=rf"bad_ckpt\.pt: {match}"):
        load_checkpoint(tmp_path / "bad_ckpt.pt")


def test_checkpoints_carry_the_run_metadata_and_its_env_config(tmp_path):
    from bimacppo_learning.checkpoint import run_meta_of
    from bimacppo_planner.decision import EnvConfig

    p, t = cfg(checkpoint_every=10)
    meta = {"env_config": EnvConfig.load(overrides={"observation.sv_clip": 30.0}).to_dict(), "map": "toy"}
    tr = Trainer(ToyIntersectionEnv, ToyScheduler(), tmp_path, p, t, run_meta=meta)
    tr.train(episodes=10)
    ck = load_checkpoint(tr.last_checkpoint)
    assert run_meta_of(ck, tr.last_checkpoint) == meta
    assert Policy.load(tr.last_checkpoint).meta == meta
    assert Policy.load(tmp_path / "policy.pt").meta["env_config"]["observation"]["sv_clip"] == 30.0
    assert run_meta_of({k: v for k, v in ck.items() if k != "run"}, "x.pt") == {}
    with pytest.raises(CheckpointError, match="x.pt: run metadata is not valid JSON"):
        run_meta_of({**ck, "run": "{not json"}, "x.pt")
    with pytest.raises(CheckpointError, match="run metadata is a list"):
        run_meta_of({**ck, "run": "[1]"}, "x.pt")


def test_config_differences_name_every_differing_leaf():
    from bimacppo_learning.checkpoint import config_differences

    saved = {"observation": {"sv_clip": 7.5, "max_sv": 3}, "reward": {"step": -0.02}}
    now = {"observation": {"sv_clip": 30.0, "max_sv": 3}, "reward": {}, "extra": 1}
    assert config_differences(saved, now) == ["extra: <absent> != 1", "observation.sv_clip: 7.5 != 30.0",
                                              "reward.step: -0.02 != <absent>"]
    assert config_differences(saved, saved) == []
    assert config_differences({"epochs": 2}, {"epochs": 3}, "ppo") == ["ppo.epochs: 2 != 3"]


def test_the_recorded_mpc_config_reads_back_and_missing_is_unknown():
    from bimacppo_mpc import MPCConfig

    from bimacppo_learning.checkpoint import mpc_config_of

    assert mpc_config_of({"env_config": {}}, "old.pt") is None          # recorded before runs kept it
    cfg = MPCConfig.load().replace(horizon=12, steer_rate_max=None)
    back = mpc_config_of({"mpc_config": cfg.to_dict()}, "x.pt")
    assert back.to_dict() == cfg.to_dict() and back.source == "x.pt (run mpc_config)"
    partial = {k: v for k, v in cfg.to_dict().items() if k != "jerk_max"}  # a key added after it was saved
    assert mpc_config_of({"mpc_config": partial}, "x.pt").jerk_max == MPCConfig.load().jerk_max
    # a key that declares what its absence meant: a run recorded before the second-start cut ran
    # without it, so its recorded controller is the uncut one, not today's default
    before_cut = cfg.to_dict()
    del before_cut["fast"]["second_start_cut"], before_cut["fast"]["steer_bound_other_side"]
    assert MPCConfig.load().fast.second_start_cut is not None
    assert mpc_config_of({"mpc_config": before_cut}, "x.pt").fast.second_start_cut is None
    # one recorded after the cut but before the side rule of the gate: the cut, either side
    before_side = cfg.to_dict()
    del before_side["fast"]["steer_bound_other_side"]
    assert MPCConfig.load().fast.steer_bound_other_side
    between = mpc_config_of({"mpc_config": before_side}, "x.pt").fast
    assert between.second_start_cut == cfg.fast.second_start_cut and not between.steer_bound_other_side
    from bimacppo_mpc.config import CONFIG_DIR
    uncut = MPCConfig.load(CONFIG_DIR / "mpc_uncut.yaml").replace(horizon=12, steer_rate_max=None)
    assert mpc_config_of({"mpc_config": before_cut}, "x.pt").to_dict() == uncut.to_dict()
    with pytest.raises(CheckpointError, match=r"^x\.pt: run metadata mpc_config: unknown key 'horizn'"):
        mpc_config_of({"mpc_config": {"horizn": 12}}, "x.pt")
    with pytest.raises(CheckpointError, match=r"^x\.pt: run metadata mpc_config: key 'horizon'"):
        mpc_config_of({"mpc_config": {"horizon": 0}}, "x.pt")
