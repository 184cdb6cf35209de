"""The training loop on the toy env: learning, reproducibility, per-env curriculum resets, logs."""
import collections
import functools
import json

import gymnasium as gym
import numpy as np
import pytest

from bimacppo_learning.ppo import PPO
from bimacppo_learning.ppo_config import load_config
from bimacppo_learning.rollout import make_vector_env, reset_each, reset_one
from toy_env import ToyEnvConfig, ToyIntersectionEnv, ToyScheduler
from bimacppo_learning.trainer import Trainer

TOY_PPO = {"minibatch_size": 64}    # 256-sample rollouts -> 4 minibatches


def toy_cfg(**train):
    base = {"rollout_steps": 128, "vector": "sync", "num_envs": 2, "batch_workers": 1,
            "tensorboard": False, "progress_bar": False,
            "checkpoint_every": 1000}
    base.update(train)
    return load_config(ppo=TOY_PPO, train=base)


class RecordingScheduler(ToyScheduler):
    """Hands out a known sequence of scenarios and records what comes back."""

    def __init__(self, seed=0):
        super().__init__(seed=seed)
        self.issued, self.updates = [], []

    def sample(self):
        ij = super().sample()
        self.issued.append(ij)
        return ij

    def update(self, i, j, ret):
        super().update(i, j, ret)
        self.updates.append((i, j, ret))


def evaluate(agent, n_per_sv=60, seed=10_000):
    env = ToyIntersectionEnv()
    wins = 0
    for n_sv in range(4):
        for k in range(n_per_sv):
            obs, _ = env.reset(seed=seed + 100 * n_sv + k, options={"n_sv": n_sv, "task": k % 3})
            done = False
            while not done:
                a, _, _ = agent.act(agent.normalize_obs(obs[None]), deterministic=True)
                obs, _, term, trunc, info = env.step(a[0])
                done = term or trunc
            wins += info["outcome"] == "success"
    return wins / (4 * n_per_sv)


def random_success(n=300):
    env = ToyIntersectionEnv()
    wins = 0
    for k in range(n):
        env.reset(seed=k, options={"n_sv": k % 4, "task": k % 3})
        env.action_space.seed(k)
        done = False
        while not done:
            _, _, term, trunc, info = env.step(env.action_space.sample())
            done = term or trunc
        wins += info["outcome"] == "success"
    return wins / n


def test_toy_env_gets_harder_with_more_svs_and_follows_the_contract():
    env = ToyIntersectionEnv()
    obs, info = env.reset(seed=0, options={"n_sv": 2, "task": 1})
    assert obs.dtype == np.float32 and obs.shape == env.observation_space.shape
    with pytest.raises(ValueError, match="n_sv"):
        env.reset(options={"n_sv": 9, "task": 0})
    with pytest.raises(ValueError, match="action"):
        env.step(np.array([7, 0, 0]))
    # the expert always succeeds; a policy ignoring the SVs collides more often as n_sv grows
    fails = []
    for n_sv in range(4):
        bad = 0
        for k in range(200):
            env.reset(seed=k, options={"n_sv": n_sv, "task": k % 3})
            done = False
            while not done:
                a = env.expert_action()
                _, _, term, trunc, info = env.step(a)
                done = term or trunc
            assert info["outcome"] == "success" and info["n_sv"] == n_sv
            assert set(info) >= {"outcome", "n_sv", "task", "episode_return"}
            # ignore the blocking flags: drive at the target speed
            env.reset(seed=k, options={"n_sv": n_sv, "task": k % 3})
            done = False
            while not done:
                a = np.array([env._targets[0], env._targets[1], env.task])
                _, _, term, trunc, info = env.step(a)
                done = term or trunc
            bad += info["outcome"] != "success"
        fails.append(bad)
    assert fails[0] == 0 and fails[0] < fails[1] < fails[2] < fails[3]


def test_agent_learns_the_toy_env(tmp_path):
    assert random_success() < 0.1
    p, t = toy_cfg()
    tr = Trainer(ToyIntersectionEnv, ToyScheduler(seed=0), tmp_path, p, t)
    res = tr.train(episodes=3500)
    assert res.episodes == 3500
    assert evaluate(tr.agent) > 0.9


def test_same_seed_sync_runs_give_identical_learning_curves(tmp_path):
    p, t = toy_cfg(rollout_steps=32)
    curves = []
    for run in ("a", "b"):
        tr = Trainer(ToyIntersectionEnv, ToyScheduler(seed=3), tmp_path / run, p, t)
        tr.train(episodes=80)
        recs = [json.loads(x) for x in (tmp_path / run / "history.jsonl").read_text().splitlines()]
        curves.append([(r["return"], r["outcome"], r["n_sv"], r["task"], r["length"]) for r in recs])
        curves[-1].append(tuple(float(v) for v in tr.agent.actor[0].weight.detach().flatten()[:20]))
    assert curves[0] == curves[1]
    tr = Trainer(ToyIntersectionEnv, ToyScheduler(seed=3), tmp_path / "c",
                 p, load_config(ppo=TOY_PPO, train={**t.__dict__, "seed": 4})[1])
    tr.train(episodes=80)
    recs = [json.loads(x) for x in (tmp_path / "c" / "history.jsonl").read_text().splitlines()]
    assert [(r["return"], r["outcome"]) for r in recs] != [c[:2] for c in curves[0][:-1]]


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_each_finished_env_is_reset_with_its_own_scheduler_sample(tmp_path, mode):
    sched = RecordingScheduler(seed=1)
    p, t = toy_cfg(rollout_steps=16, vector=mode, num_envs=2, tensorboard=True)
    tr = Trainer(ToyIntersectionEnv, sched, tmp_path, p, t)
    res = tr.train(episodes=40)
    recs = [json.loads(x) for x in (tmp_path / "history.jsonl").read_text().splitlines()]
    # the budget is exact, and every recorded episode ran the scenario the scheduler issued for it
    assert res.episodes == len(recs) == len(sched.updates) == 40
    assert [r["episode"] for r in recs] == list(range(1, 41))
    issued = collections.Counter(sched.issued)
    ran = collections.Counter((r["n_sv"], r["task"]) for r in recs)
    assert all(ran[k] <= issued[k] for k in ran)
    assert [(u[0], u[1]) for u in sched.updates] == [(r["n_sv"], r["task"]) for r in recs]
    assert [u[2] for u in sched.updates] == pytest.approx([r["episode_return"] for r in recs])
    assert [r["return"] for r in recs] == pytest.approx([r["episode_return"] for r in recs], abs=1e-5)
    assert set(r["outcome"] for r in recs) <= {"success", "collision", "timeout"}
    assert "count_0_0" in recs[-1]["scheduler"]
    assert list((tmp_path / "tb").glob("events.out.tfevents.*"))
    assert (tmp_path / "policy.pt").exists()


def test_masked_reset_gives_each_env_its_own_options():
    venv = make_vector_env(ToyIntersectionEnv, 2, "async")
    try:
        obs = reset_each(venv, [1, 2], [{"n_sv": 0, "task": 0}, {"n_sv": 3, "task": 2}])
        sv_slots = obs[:, -12:].reshape(2, 3, 4)[:, :, 3]
        assert sv_slots[0].sum() == 0 and sv_slots[1].sum() == 3
        o1, info = reset_one(venv, 0, 5, {"n_sv": 2, "task": 1})
        assert o1[-12:].reshape(3, 4)[:, 3].sum() == 2 and info["n_sv"] == 2
    finally:
        venv.close()


def test_truncation_path_records_timeouts_as_truncations(tmp_path):
    """Timeouts as truncations: the loop must keep the episode records right and bootstrap."""
    env_fn = functools.partial(ToyIntersectionEnv, ToyEnvConfig(timeout_terminates=False))
    p, t = toy_cfg(rollout_steps=64)
    tr = Trainer(env_fn, ToyScheduler(seed=0), tmp_path, p, t)
    res = tr.train(episodes=150)
    recs = [json.loads(x) for x in (tmp_path / "history.jsonl").read_text().splitlines()]
    timeouts = [r for r in recs if r["outcome"] == "timeout"]
    assert timeouts and all(not r["terminated"] for r in timeouts)
    assert all(r["terminated"] for r in recs if r["outcome"] != "timeout")
    assert res.episodes == 150


class NoOutcomeEnv(ToyIntersectionEnv):
    def step(self, action):
        obs, r, term, trunc, info = super().step(action)
        info.pop("outcome", None)
        return obs, r, term, trunc, info


class BoxActionEnv(ToyIntersectionEnv):
    def __init__(self):
        super().__init__()
        self.action_space = gym.spaces.Box(-1, 1, (3,))


def test_bad_env_or_arguments_give_clear_errors(tmp_path):
    p, t = toy_cfg()
    with pytest.raises(ValueError, match="outcome"):
        Trainer(NoOutcomeEnv, ToyScheduler(), tmp_path / "a", p, t).train(episodes=5)
    with pytest.raises(ValueError, match="MultiDiscrete"):
        Trainer(BoxActionEnv, ToyScheduler(), tmp_path / "b", p, t).train(episodes=5)
    with pytest.raises(ValueError, match="episodes"):
        Trainer(ToyIntersectionEnv, ToyScheduler(), tmp_path / "c", p, t).train(episodes=0)
    with pytest.raises(TypeError, match="scheduler"):
        Trainer(ToyIntersectionEnv, object(), tmp_path / "d", p, t)


class RaggedInfoEnv(ToyIntersectionEnv):
    """An info value whose shape differs between envs: Gymnasium's vector env cannot stack it,
    after the workers have answered the step."""

    def step(self, action):
        obs, r, term, trunc, info = super().step(action)
        info["ragged"] = np.zeros(1 + int(self.np_random.integers(0, 3)))
        return obs, r, term, trunc, info


def test_an_error_in_an_async_step_ends_the_run_with_that_error(tmp_path):
    """The error surfaces, the worker processes end, and closing does not wait for a step that
    will never be answered (it did, forever, hiding the error)."""
    import threading
    p, t = toy_cfg(rollout_steps=16, vector="async", num_envs=2)
    caught = []

    def run():
        try:
            Trainer(RaggedInfoEnv, ToyScheduler(), tmp_path, p, t).train(episodes=40)
        except Exception as e:  # noqa: BLE001 - the test inspects it
            caught.append(e)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    th.join(120)
    assert not th.is_alive(), "training hung after the failed step"
    assert caught and isinstance(caught[0], ValueError) and "broadcast" in str(caught[0])


class ThreadCountChangingEnv(ToyIntersectionEnv):
    """The toy env that changes the process's OpenMP thread count in every step, as a numba
    parallel call (the batched NMPC) can: torch's operators read that count."""

    def step(self, action):
        import torch

        torch.set_num_threads(3)
        return super().step(action)


def test_the_policy_acts_on_its_configured_threads_whatever_the_env_step_left(tmp_path, monkeypatch):
    """The trainer sets torch's acting threads back after every env step and each update, so a
    step that changed the thread count cannot make the policy wake idle threads for tiny ops."""
    import torch

    p, t = toy_cfg(rollout_steps=16, torch_threads=1, update_threads=2)
    tr = Trainer(ThreadCountChangingEnv, ToyScheduler(seed=0), tmp_path, p, t)
    acting, updating = [], []
    act, update = PPO.act, PPO.update
    monkeypatch.setattr(PPO, "act", lambda *a, **k: (acting.append(torch.get_num_threads()), act(*a, **k))[1])
    monkeypatch.setattr(PPO, "update", lambda *a, **k: (updating.append(torch.get_num_threads()), update(*a, **k))[1])
    tr.train(episodes=12)
    assert len(acting) > 16 and len(updating) >= 1
    assert set(acting) == {1} and set(updating) == {2}


def test_tensorboard_gets_every_kth_episode_and_the_history_every_episode(tmp_path):
    """tensorboard_every = k: the per-episode and curriculum tags get the episodes k, 2k, ...;
    history.jsonl gets them all."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    p, t = toy_cfg(rollout_steps=16, tensorboard=True, tensorboard_every=3)
    tr = Trainer(ToyIntersectionEnv, ToyScheduler(seed=0), tmp_path, p, t)
    tr.train(episodes=10)
    recs = [json.loads(x) for x in (tmp_path / "history.jsonl").read_text().splitlines()]
    assert [r["episode"] for r in recs] == list(range(1, len(recs) + 1)) and len(recs) >= 10
    acc = EventAccumulator(str(tmp_path / "tb"))
    acc.Reload()
    tags = acc.Tags()["scalars"]
    curriculum = [tag for tag in tags if tag.startswith("curriculum/")]
    assert curriculum
    want = [e for e in range(1, len(recs) + 1) if e % 3 == 0]
    for tag in ["episode/return", "episode/success_rate", *curriculum]:
        assert [ev.step for ev in acc.Scalars(tag)] == want, tag
    returns = {r["episode"]: r["return"] for r in recs}
    assert [ev.value for ev in acc.Scalars("episode/return")] == pytest.approx([returns[e] for e in want])


@pytest.mark.parametrize("critic_thread", [True, False])
def test_the_trainer_hands_the_critic_thread_setting_to_every_update(tmp_path, monkeypatch, critic_thread):
    p, t = toy_cfg(rollout_steps=16, critic_thread=critic_thread)
    seen = []
    update = PPO.update
    monkeypatch.setattr(PPO, "update", lambda *a, **k: (seen.append(k.get("critic_thread")), update(*a, **k))[1])
    Trainer(ToyIntersectionEnv, ToyScheduler(seed=0), tmp_path, p, t).train(episodes=6)
    assert seen and set(seen) == {critic_thread}


def test_training_histories_are_the_same_with_the_critic_on_its_own_thread_or_not(tmp_path):
    """The critic's thread changes where the update runs, not what it computes: two toy runs
    differing only in critic_thread write the same history."""
    runs = {}
    for flag in (True, False):
        p, t = toy_cfg(rollout_steps=32, critic_thread=flag)
        d = tmp_path / str(flag)
        Trainer(ToyIntersectionEnv, ToyScheduler(seed=0), d, p, t).train(episodes=20)
        runs[flag] = [{k: v for k, v in json.loads(x).items() if not k.endswith("_s") and k != "time"}
                      for x in (d / "history.jsonl").read_text().splitlines()]
    assert len(runs[True]) >= 20 and runs[True] == runs[False]
