"""Behaviour-cloned warm start: the action-space 'yield' teacher, the clone, the CLI's files."""
import json

import numpy as np
import pytest

from bimacppo_planner.agent import load_policy
from bimacppo_planner.decision import ConfigError, EnvConfig
from bimacppo_learning.env import IntersectionEnv
from bimacppo_learning.evaluate import eval_seed
from bimacppo_learning.imitation import CloneConfig, ImitationConfig, YieldTeacher, behaviour_clone, collect, main
from bimacppo_learning.ppo import PPO
from bimacppo_learning.trainer import load_agent

EXT = EnvConfig.load(__import__("pathlib").Path(__import__("bimacppo_learning").__file__).parent
                     / "config" / "env_extended.yaml")


@pytest.fixture(scope="module")
def env():
    # the teacher's actions were tuned with the NMPC without rate bounds, the controller the
    # shipped clone was made and is run with (policies/README.md)
    from bimacppo_mpc import MPCConfig
    from conftest import REPO
    return IntersectionEnv(config=EXT, mpc_config=MPCConfig.load(
        REPO / "bimacppo_mpc/bimacppo_mpc/config/mpc_unbounded.yaml"))


def test_teacher_crosses_busy_junctions_without_collision(env):
    """The teacher is only worth cloning if it is safe where PPO is not: N_sv = 3, every task."""
    cfg = ImitationConfig.load(nvec=EXT.nvec)
    teacher = YieldTeacher(env, cfg.teacher)
    stopped = 0
    for j in range(3):
        for k in range(4):
            env.reset(options={"n_sv": 3, "task": j, "scenario_seed": eval_seed(j, 3, k)})
            teacher.reset()
            while True:
                a = teacher.act()
                stopped += int(tuple(a) == tuple(cfg.teacher.stop))
                _, _, term, trunc, info = env.step(a)
                if term or trunc:
                    break
            assert info["outcome"] == "success", (j, k, info["outcome"])
    assert stopped > 0   # it did wait somewhere, not just drive through


def test_clone_matches_the_teacher_and_checkpoint_feeds_init_policy(env, tmp_path):
    cfg = ImitationConfig.load(nvec=EXT.nvec)
    cfg = ImitationConfig(6, cfg.seed_base, cfg.n_sv_probs, cfg.teacher, cfg.clone, cfg.source)
    O, A, R, outcomes = collect(env, cfg, seed=1)
    assert len(O) == len(A) == len(R) > 100 and sum(outcomes.values()) == 6
    assert np.all(np.isfinite(R))
    agent = PPO(EXT.obs_dim, EXT.nvec, seed=0)
    before = float((agent.act(agent.normalize_obs(O), deterministic=True)[0] == A).all(-1).mean())
    small = CloneConfig(epochs=40, batch_size=64, lr=1e-3, gamma=0.99)   # ~300 samples: smaller batches
    stats = behaviour_clone(agent, O, A, R, small, seed=0)
    assert stats["accuracy"] > 0.9 > before


def test_cli_writes_checkpoint_policy_and_report(tmp_path, capsys):
    src = ImitationConfig.load()
    cfg = tmp_path / "imitation.yaml"
    text = open(src.source).read().replace("episodes: 800", "episodes: 4").replace("epochs: 40", "epochs: 3")
    cfg.write_text(text)
    env_cfg = tmp_path / "env.yaml"
    env_cfg.write_text("action:\n  decision_every: 3\n")
    out = tmp_path / "bc"
    from bimacppo_mpc import MPCConfig
    from conftest import REPO
    unbounded = REPO / "bimacppo_mpc/bimacppo_mpc/config/mpc_unbounded.yaml"
    assert main(["--out-dir", str(out), "--config", str(cfg), "--env-config", str(env_cfg), "--no-progress",
                 "--mpc-config", str(unbounded)]) == 0
    rep = json.loads((out / "imitation.json").read_text())
    assert rep["episodes"] == 4 and sum(rep["teacher_outcomes"].values()) == 4 and 0 <= rep["accuracy"] <= 1
    agent = load_agent(out / "checkpoint.pt")          # what bimacppo-train --init-policy reads
    pol = load_policy(out / "policy.pt")
    assert agent.obs_dim == pol.obs_dim
    assert "--init-policy" in capsys.readouterr().out
    # both files record how the clone was made, so --init-policy checks env and MPC config like a run's
    from bimacppo_learning.checkpoint import load_checkpoint, run_meta_of
    from bimacppo_learning.cli import check_checkpoint_fits
    meta = run_meta_of(load_checkpoint(out / "checkpoint.pt"), out / "checkpoint.pt")
    assert meta["mpc_config"] == pol.meta["mpc_config"] == MPCConfig.load(unbounded).to_dict()
    assert meta["env_config"] == EnvConfig.load(env_cfg).to_dict()
    fits = lambda env, mpc: check_checkpoint_fits(out / "checkpoint.pt", agent.obs_dim, agent.nvec, meta, env, mpc)  # noqa: E731
    assert fits(EnvConfig.load(env_cfg), MPCConfig.load(unbounded)) is None
    assert "steer_rate_max: None != " in fits(EnvConfig.load(env_cfg), MPCConfig.load())
    assert "another env config" in fits(EnvConfig.load(), MPCConfig.load(unbounded))
    bad = tmp_path / "mpc.yaml"
    bad.write_text("horizon: 0\n")
    assert main(["--out-dir", str(tmp_path / "o"), "--config", str(cfg), "--mpc-config", str(bad), "--no-progress"]) == 2
    assert "horizon" in capsys.readouterr().err and not (tmp_path / "o").exists()


@pytest.mark.parametrize("edit, key", [
    (("right: [1, 2, 1]", "right: [1, 9, 1]"), "teacher.go.right"),
    (("stop: [0, 0, 1]", "stop: [0, 0]"), "teacher.stop"),
    (("n_sv_probs: [0.1, 0.2, 0.3, 0.4]", "n_sv_probs: [0.5, 0.6]"), "n_sv_probs"),
    (("gamma: 0.99", "gamma: 2.0"), "clone.gamma"),
    (("episodes: 800", "episodes: many"), "episodes"),
])
def test_bad_config_is_named(tmp_path, capsys, edit, key):
    text = open(ImitationConfig.load().source).read()
    assert edit[0] in text
    bad = tmp_path / "imitation.yaml"
    bad.write_text(text.replace(edit[0], edit[1]))
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        ImitationConfig.load(bad, nvec=EXT.nvec)
    assert main(["--out-dir", str(tmp_path / "o"), "--config", str(bad), "--no-progress"]) == 2
    assert key in capsys.readouterr().err
    assert not (tmp_path / "o" / "checkpoint.pt").exists()


def test_missing_config_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        ImitationConfig.load(tmp_path / "nope.yaml")
