"""bimacppo-train / bimacppo-evaluate end to end on the real environment (tiny budgets)."""
import csv
import json

import pytest

from bimacppo_learning.cli import evaluate_main, train_main

SMALL = """
ppo:
  minibatch_size: 64
  epochs: 2
train:
  num_envs: 1
  vector: sync
  rollout_steps: 128
  checkpoint_every: 3
  tensorboard: true
  progress_bar: false
"""


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    d = tmp_path_factory.mktemp("train")
    cfg = d / "ppo.yaml"
    cfg.write_text(SMALL)
    run = d / "run"
    rc = train_main(["--curriculum", "bimab", "--episodes", "4", "--seed", "1", "--run-dir", str(run),
                     "--ppo-config", str(cfg), "--no-progress"])
    assert rc == 0
    return d, cfg, run


def test_train_writes_history_checkpoints_tensorboard_and_policy(trained):
    _, _, run = trained
    recs = [json.loads(line) for line in (run / "history.jsonl").read_text().splitlines()]
    assert [r["episode"] for r in recs] == [1, 2, 3, 4]
    for r in recs:
        assert r["outcome"] in ("success", "collision", "timeout")
        assert 0 <= r["n_sv"] <= 3 and 0 <= r["task"] <= 2
        # the BiMAB's weights / probabilities / counts are logged every episode
        assert "cluster_prob_0" in r["scheduler"] and any(k.startswith("arm_") for k in r["scheduler"])
    assert (run / "policy.pt").is_file()
    assert list((run / "checkpoints").glob("*.pt"))
    assert list((run / "tb").glob("events.out.tfevents.*"))
    assert json.loads((run / "run.json").read_text())["curriculum"] == "bimab"


def test_train_resumes_where_it_stopped(trained):
    _, cfg, run = trained
    rc = train_main(["--curriculum", "bimab", "--episodes", "6", "--seed", "1", "--run-dir", str(run),
                     "--ppo-config", str(cfg), "--no-progress", "--resume"])
    assert rc == 0
    recs = [json.loads(line) for line in (run / "history.jsonl").read_text().splitlines()]
    assert [r["episode"] for r in recs] == list(range(1, 7))


def test_train_rejects_bad_config(tmp_path, capsys):
    bad = tmp_path / "ppo.yaml"
    bad.write_text("ppo:\n  epochs: -3\n")
    assert train_main(["--episodes", "2", "--run-dir", str(tmp_path / "r"), "--ppo-config", str(bad)]) == 2
    assert "epochs" in capsys.readouterr().err


def test_evaluate_protocol_table_and_csv(trained, tmp_path, capsys):
    _, _, run = trained
    out = tmp_path / "table"
    rc = evaluate_main([str(run / "policy.pt"), "--episodes", "2", "--n-sv", "0", "3", "--tasks", "left",
                        "--workers", "1", "--out", str(out)])
    assert rc == 0
    md = out.with_suffix(".md").read_text()
    assert "N_sv=0" in md and "N_sv=3" in md and "| left |" in md
    rows = list(csv.DictReader(out.with_suffix(".csv").open()))
    assert [(r["task"], r["n_sv"], r["episodes"]) for r in rows] == [("left", "0", "2"), ("left", "3", "2")]
    for r in rows:
        total = float(r["success_pct"]) + float(r["collision_pct"]) + float(r["timeout_pct"])
        assert total == pytest.approx(100.0)


def test_evaluate_takes_an_mpc_config_and_refuses_a_broken_one(tmp_path, capsys):
    from bimacppo_learning.evaluate import evaluate
    from conftest import REPO
    unbounded = REPO / "bimacppo_mpc/bimacppo_mpc/config/mpc_unbounded.yaml"
    kw = dict(map_id="dual_lane_4way", n_svs=[0], tasks=[1], episodes=1, workers=1, random_row=False)
    bounded = evaluate(None, **kw)[0].comfort
    free = evaluate(None, mpc_config=unbounded, **kw)[0].comfort
    # the same policy and scenario with another controller: the applied commands differ
    assert (bounded.ticks, bounded.jerk_sq) != (free.ticks, free.jerk_sq)
    bad = tmp_path / "mpc.yaml"
    bad.write_text("steer_rate_maxx: 1.0\n")
    assert evaluate_main(["--episodes", "1", "--n-sv", "0", "--tasks", "left", "--no-random-row",
                          "--mpc-config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "steer_rate_maxx" in err and "Traceback" not in err


def test_evaluate_rejects_corrupt_policy(tmp_path, capsys):
    bad = tmp_path / "policy.pt"
    bad.write_bytes(b"\x00" * 100)
    assert evaluate_main([str(bad), "--episodes", "1"]) == 2
    assert "policy.pt" in capsys.readouterr().err


def test_report_draws_figures_and_table_i(trained, tmp_path):
    from bimacppo_learning.report import main as report_main

    _, _, run = trained
    out = tmp_path / "img" / "run"
    assert report_main([str(run), "--out", str(out), "--window", "2"]) == 0
    for suffix in ("_success.png", "_success_by_nsv.png", "_fig5_clusters.png", "_fig6_arms.png", "_probs.png"):
        p = out.parent / (out.name + suffix)
        assert p.is_file() and p.stat().st_size > 5_000, p
    table = (out.parent / (out.name + "_table1.md")).read_text()
    rows = [line for line in table.splitlines() if line.startswith("| all |")]
    assert rows and int(rows[0].split("|")[2]) >= 6   # every recorded episode was sampled once


def test_report_rejects_a_directory_without_history(tmp_path, capsys):
    from bimacppo_learning.report import main as report_main

    assert report_main([str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "history.jsonl" in err and err.startswith("bimacppo-report: error: ")


def test_policy_carries_its_env_config(trained):
    from bimacppo_planner.agent import HighLevelPlanner, env_config_of, load_policy
    from bimacppo_planner.decision import EnvConfig

    _, _, run = trained
    pol = load_policy(run / "policy.pt")
    assert pol.meta["curriculum"] == "bimab" and pol.meta["seed"] == 1
    assert env_config_of(pol) == EnvConfig.load()
    assert HighLevelPlanner(pol, __import__("bimacppo_sim").load_map("dual_lane_4way")).cfg == EnvConfig.load()


def test_train_on_the_straight_road_folds_tasks_and_slows_svs(trained, tmp_path, capsys):
    """Every curriculum draws left/straight/right; the 3-lane road has only "straight", so
    training there (the overtaking fine-tune, from a checkpoint) must fold the tasks, not
    crash on the first reset."""
    _, cfg, run = trained
    ckpt = sorted((run / "checkpoints").glob("*.pt"))[-1]
    out = tmp_path / "overtake"
    rc = train_main(["--curriculum", "random", "--episodes", "3", "--seed", "2", "--run-dir", str(out),
                     "--map", "three_lane_straight", "--slow-svs", "2", "--init-policy", str(ckpt),
                     "--ppo-config", str(cfg), "--no-progress"])
    assert rc == 0
    assert "only the task(s) ['straight']" in capsys.readouterr().err
    recs = [json.loads(line) for line in (out / "history.jsonl").read_text().splitlines()]
    assert len(recs) == 3 and all(r["outcome"] in ("success", "collision", "timeout") for r in recs)
    assert json.loads((out / "run.json").read_text())["slow_svs"] == 2
    assert train_main(["--episodes", "2", "--run-dir", str(tmp_path / "r"), "--slow-svs", "7"]) == 2
    assert "--slow-svs" in capsys.readouterr().err


# --- refusals: one `bimacppo-<tool>: error: ...` line, exit status 2, the run directory untouched ---


def _one_error_line(err: str, prog: str) -> str:
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith(("INFO ", "WARNING "))]
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: "), err
    return lines[0]


def _snapshot(run):
    return {p.relative_to(run): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


@pytest.fixture
def env_yaml(tmp_path):
    def write(text):
        path = tmp_path / f"env{abs(hash(text))}.yaml"
        path.write_text(text)
        return path
    return write


def test_resume_with_another_env_config_is_refused_and_leaves_the_run_as_it_was(trained, env_yaml, capsys):
    _, cfg, run = trained
    before = _snapshot(run)
    rc = train_main(["--episodes", "8", "--seed", "1", "--run-dir", str(run), "--ppo-config", str(cfg),
                     "--no-progress", "--resume", "--env-config", str(env_yaml("observation:\n  sv_clip: 30.0\n"))])
    assert rc == 2
    line = _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert "another env config" in line and "observation.sv_clip: 7.5 != 30.0" in line
    assert _snapshot(run) == before          # run.json, history and checkpoints as they were


def test_resume_with_another_ppo_config_or_without_resume_is_refused_before_writing(trained, tmp_path, capsys):
    _, cfg, run = trained
    before = _snapshot(run)
    other = tmp_path / "ppo.yaml"
    other.write_text(SMALL.replace("epochs: 2", "epochs: 3"))
    assert train_main(["--episodes", "8", "--seed", "1", "--run-dir", str(run), "--ppo-config", str(other),
                       "--no-progress", "--resume"]) == 2
    assert "ppo.epochs: 2 != 3" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert train_main(["--episodes", "8", "--seed", "1", "--run-dir", str(run), "--ppo-config", str(cfg),
                       "--no-progress"]) == 2
    assert "--resume" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert _snapshot(run) == before


def test_init_policy_refusals(trained, tmp_path, env_yaml, capsys):
    _, cfg, run = trained
    ckpt = sorted((run / "checkpoints").glob("*.pt"))[-1]
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(ckpt.read_bytes()[:200])
    cases = [
        ([str(tmp_path / "missing.pt")], "missing.pt: no such file"),
        ([str(corrupt)], "corrupt.pt: not a readable torch file"),
        ([str(ckpt), "--env-config", str(env_yaml("observation:\n  max_sv: 2\n"))],
         "its agent takes observations of size 16 and actions nvec=[5, 5, 3]; this run's env config gives 12"),
        ([str(ckpt), "--env-config", str(env_yaml("observation:\n  sv_clip: 30.0\nreward:\n  step: -0.1\n"))],
         "observation.sv_clip: 7.5 != 30.0; reward.step: -0.02 != -0.1"),
    ]
    for k, (extra, says) in enumerate(cases):
        out = tmp_path / f"r{k}"
        rc = train_main(["--episodes", "2", "--run-dir", str(out), "--ppo-config", str(cfg), "--no-progress",
                         "--init-policy", *extra])
        assert rc == 2, extra
        assert says in _one_error_line(capsys.readouterr().err, "bimacppo-train"), extra
        assert not out.exists()


def test_a_fine_tune_can_start_from_a_policy_export_whose_critic_warms_up_first(trained, tmp_path, env_yaml, capsys,
                                                                                caplog):
    """A policy export has no critic: the fine-tune takes its actor and normaliser, a fresh
    critic and the packaged PPO config with the export's networks; ppo.critic_warmup_updates
    holds the actor still while that critic is fitted (the actor is then the export's exactly),
    a warm-up of 0 is warned about, and an ensemble is refused on one line before writing."""
    import logging

    import torch

    from bimacppo_learning.checkpoint import load_checkpoint, make_ensemble
    from bimacppo_learning.trainer import load_fine_tune_source

    _, cfg, run = trained
    export = run / "policy.pt"
    exported = torch.load(export, weights_only=True)
    agent, meta, fresh = load_fine_tune_source(export, seed=4)
    assert fresh and meta["env_config"] == exported["meta"]["env_config"]
    assert all(torch.equal(exported["actor"][k], v) for k, v in agent.actor.state_dict().items())
    assert torch.equal(torch.as_tensor(agent.obs_rms.mean), torch.as_tensor(exported["obs_rms"]["mean"]))
    assert agent.cfg.epochs == 20                              # the packaged config: an export records none
    assert not load_fine_tune_source(sorted((run / "checkpoints").glob("*.pt"))[-1])[2]

    warm = tmp_path / "warm.yaml"
    warm.write_text(SMALL.replace("ppo:\n", "ppo:\n  critic_warmup_updates: 1000\n"))
    out = tmp_path / "held"
    assert train_main(["--episodes", "2", "--no-progress", "--init-policy", str(export), "--ppo-config", str(warm),
                       "--run-dir", str(out)]) == 0
    tuned = load_checkpoint(sorted((out / "checkpoints").glob("*.pt"))[-1])
    assert tuned["counters"]["updates"] >= 1 and tuned["config"]["ppo"]["critic_warmup_updates"] == 1000
    assert all(torch.equal(exported["actor"][k], v) for k, v in tuned["agent"]["actor"].items())
    assert set(_tb_scalars(out, "update/actor_fitted")) == {0.0}

    moved = tmp_path / "moved"
    with caplog.at_level(logging.WARNING):
        assert train_main(["--episodes", "2", "--no-progress", "--init-policy", str(export), "--ppo-config",
                           str(cfg), "--run-dir", str(moved)]) == 0
    assert "critic_warmup_updates is 0" in caplog.text
    tuned = load_checkpoint(sorted((moved / "checkpoints").glob("*.pt"))[-1])
    assert not all(torch.equal(exported["actor"][k], v) for k, v in tuned["agent"]["actor"].items())

    caplog.clear()
    with caplog.at_level(logging.WARNING):   # a refused export is refused, not warned about
        assert train_main(["--episodes", "2", "--no-progress", "--init-policy", str(export), "--env-config",
                           str(env_yaml("observation:\n  max_sv: 2\n")), "--run-dir", str(tmp_path / "r")]) == 2
    assert "pass the --env-config it was trained with" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert "critic_warmup_updates" not in caplog.text and not (tmp_path / "r").exists()

    ens = make_ensemble([export, export], tmp_path / "ens.pt")
    capsys.readouterr()
    assert train_main(["--episodes", "2", "--no-progress", "--init-policy", str(ens), "--run-dir",
                       str(tmp_path / "e")]) == 2
    assert "is an ensemble of policies" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert not (tmp_path / "e").exists()


def test_a_fine_tune_records_its_whole_lineage_and_a_resume_keeps_it(trained, tmp_path):
    """A fine-tune records the file it started from (name, SHA-256 of its bytes, curriculum,
    map, seed, episodes) in run.json, its checkpoints and its exported policy; a fine-tune of
    that fine-tune nests the first record, so a policy file names every file it descends from;
    a resumed run keeps the lineage of its checkpoint; a run from scratch records none."""
    import hashlib

    import torch

    from bimacppo_learning.checkpoint import load_checkpoint, run_meta_of

    _, cfg, run = trained
    export = run / "policy.pt"
    first, second = tmp_path / "first", tmp_path / "second"
    assert train_main(["--episodes", "2", "--no-progress", "--init-policy", str(export), "--ppo-config", str(cfg),
                       "--run-dir", str(first)]) == 0
    src_meta = torch.load(export, weights_only=True)["meta"]
    assert "fine_tuned_from" not in src_meta                                  # trained from scratch
    rec = torch.load(first / "policy.pt", weights_only=True)["meta"]["fine_tuned_from"]
    assert rec == {"file": "policy.pt", "sha256": hashlib.sha256(export.read_bytes()).hexdigest(),
                   "curriculum": src_meta["curriculum"], "map": src_meta["map"], "seed": src_meta["seed"],
                   "episodes": src_meta["episodes"]}
    ckpt = sorted((first / "checkpoints").glob("*.pt"))[-1]
    assert run_meta_of(load_checkpoint(ckpt), ckpt)["fine_tuned_from"] == rec
    assert json.loads((first / "run.json").read_text())["fine_tuned_from"] == rec

    assert train_main(["--episodes", "2", "--no-progress", "--init-policy", str(ckpt), "--seed", "3",
                       "--run-dir", str(second)]) == 0
    rec2 = torch.load(second / "policy.pt", weights_only=True)["meta"]["fine_tuned_from"]
    assert rec2["file"] == ckpt.name and rec2["sha256"] == hashlib.sha256(ckpt.read_bytes()).hexdigest()
    assert rec2["episodes"] == load_checkpoint(ckpt)["counters"]["episodes"] and rec2["fine_tuned_from"] == rec

    assert train_main(["--episodes", "4", "--no-progress", "--resume", "--seed", "3", "--ppo-config", str(cfg),
                       "--run-dir", str(second)]) == 0
    assert torch.load(second / "policy.pt", weights_only=True)["meta"]["fine_tuned_from"] == rec2


def _fine_tune_args(trained):
    """(PPO config, the trained run, the argv of a 2-episode fine-tune from its newest checkpoint)."""
    _, cfg, run = trained
    ckpt = sorted((run / "checkpoints").glob("*.pt"))[-1]
    return cfg, run, ["--episodes", "2", "--ppo-config", str(cfg), "--no-progress", "--init-policy", str(ckpt)]


def _tb_scalars(run, tag):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run / "tb"))
    acc.Reload()
    return [e.value for e in acc.Scalars(tag)]


def test_a_fine_tune_trains_under_its_ppo_config_and_records_the_one_it_trained_under(trained, tmp_path, capsys):
    """Without --ppo-config a fine-tune keeps its source's PPO settings (and says so in its
    checkpoints); with one, the updates run under that file (3 epochs here, not the source's 2);
    a file that changes the networks is refused before anything is written."""
    from bimacppo_learning.checkpoint import load_checkpoint

    cfg, run, base = _fine_tune_args(trained)
    ckpt = base[-1]
    inherit = tmp_path / "inherit"
    assert train_main(["--episodes", "2", "--no-progress", "--init-policy", ckpt, "--run-dir", str(inherit)]) == 0
    saved = load_checkpoint(sorted((inherit / "checkpoints").glob("*.pt"))[-1])["config"]["ppo"]
    assert (saved["epochs"], saved["minibatch_size"]) == (2, 64)        # the source's, not ppo.yaml's 20 / 512
    assert set(_tb_scalars(inherit, "update/epochs")) == {2.0}
    other = tmp_path / "ppo3.yaml"
    other.write_text(SMALL.replace("epochs: 2", "epochs: 3\n  entropy_coef: 0.05"))
    own = tmp_path / "own"
    assert train_main(["--episodes", "2", "--no-progress", "--init-policy", ckpt, "--ppo-config", str(other),
                       "--run-dir", str(own)]) == 0
    saved = load_checkpoint(sorted((own / "checkpoints").glob("*.pt"))[-1])["config"]["ppo"]
    assert (saved["epochs"], saved["entropy_coef"]) == (3, 0.05)
    assert set(_tb_scalars(own, "update/epochs")) == {3.0}
    capsys.readouterr()
    wide = tmp_path / "wide.yaml"
    wide.write_text(SMALL.replace("ppo:\n", "ppo:\n  hidden_sizes: [32]\n"))
    refused = tmp_path / "refused"
    assert train_main(["--episodes", "2", "--no-progress", "--init-policy", ckpt, "--ppo-config", str(wide),
                       "--run-dir", str(refused)]) == 2
    line = _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert "hidden_sizes ((256, 128) -> (32,))" in line and "cannot change in a fine-tune" in line
    assert not refused.exists()


def test_a_fine_tune_may_change_the_reward_when_told_but_a_resume_may_not(trained, tmp_path, env_yaml, capsys):
    """The reward is the task a run trains for: a fine-tune given --fine-tune-reward trains with
    its own and records it; without the flag, and on a resume (one run continued), another
    reward is refused; another observation is refused even with the flag."""
    cfg, run, base = _fine_tune_args(trained)
    terminal = env_yaml("reward:\n  timeout_mode: truncate\n  step: -0.1\n")
    out = tmp_path / "tuned"
    assert train_main([*base, "--run-dir", str(out), "--env-config", str(terminal)]) == 2
    line = _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert "reward.step: -0.02 != -0.1" in line and "--fine-tune-reward" in line and not out.exists()
    seen = env_yaml("observation:\n  sv_clip: 30.0\nreward:\n  step: -0.1\n")
    assert train_main([*base, "--run-dir", str(out), "--env-config", str(seen), "--fine-tune-reward"]) == 2
    line = _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert "observation.sv_clip: 7.5 != 30.0; checkpoint" in line and "reward" not in line
    assert train_main(["--episodes", "2", "--run-dir", str(tmp_path / "x"), "--fine-tune-reward"]) == 2
    assert "needs --init-policy" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert train_main([*base, "--run-dir", str(out), "--env-config", str(terminal), "--fine-tune-reward"]) == 0
    reward = json.loads((out / "run.json").read_text())["env_config"]["reward"]
    assert (reward["timeout_mode"], reward["step"]) == ("truncate", -0.1)
    before = _snapshot(run)
    assert train_main(["--episodes", "8", "--run-dir", str(run), "--ppo-config", str(cfg), "--no-progress",
                       "--resume", "--env-config", str(terminal)]) == 2
    line = _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert "reward.step: -0.02 != -0.1" in line and "reward.timeout_mode" in line
    assert _snapshot(run) == before


def test_a_fine_tune_may_change_how_actions_decode_only_when_told(trained, tmp_path, env_yaml, capsys):
    """How A3 decodes is part of the task: another action section is refused for --init-policy
    unless --fine-tune-action says so (the error names the field and the flag); with it the run
    records the new decoding; the heads' sizes are compared all the same; --resume keeps its run's."""
    cfg, run, base = _fine_tune_args(trained)
    chosen = env_yaml("action:\n  lane_change_from: chosen\n")
    out = tmp_path / "chosen"
    assert train_main([*base, "--run-dir", str(out), "--env-config", str(chosen)]) == 2
    line = _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert "action.lane_change_from: route != chosen" in line and "--fine-tune-action" in line and not out.exists()
    fewer = env_yaml("action:\n  lane_change_from: chosen\n  speeds: [0.0, 4.0, 8.0]\n")
    assert train_main([*base, "--run-dir", str(out), "--env-config", str(fewer), "--fine-tune-action"]) == 2
    assert "nvec" in _one_error_line(capsys.readouterr().err, "bimacppo-train") and not out.exists()
    assert train_main(["--episodes", "2", "--run-dir", str(tmp_path / "x"), "--fine-tune-action"]) == 2
    assert "needs --init-policy" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert train_main([*base, "--run-dir", str(out), "--env-config", str(chosen), "--fine-tune-action"]) == 0
    assert json.loads((out / "run.json").read_text())["env_config"]["action"]["lane_change_from"] == "chosen"
    before = _snapshot(run)
    assert train_main(["--episodes", "8", "--run-dir", str(run), "--ppo-config", str(cfg), "--no-progress",
                       "--resume", "--env-config", str(chosen)]) == 2
    assert "action.lane_change_from: route != chosen" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert _snapshot(run) == before


def test_report_refuses_a_bad_window_on_one_line(trained, tmp_path, capsys):
    from bimacppo_learning.report import main as report_main

    _, _, run = trained
    for w in ("-3", "0"):
        assert report_main([str(run), "--out", str(tmp_path / "x"), "--window", w]) == 2
        assert "--window must be >= 1" in _one_error_line(capsys.readouterr().err, "bimacppo-report")
    assert report_main([str(run), "--out", str(tmp_path / "x"), "--window", "1"]) == 0


def test_report_counts_episodes_per_second_over_every_resumed_segment():
    from bimacppo_learning.report import summary, training_wall_s

    # 10 episodes in 20 s, then a resume (wall_s restarts at 0) and 10 more in 5 s
    recs = [{"episode": k, "n_sv": 0, "outcome": "success", "wall_s": 2.0 * k} for k in range(1, 11)]
    recs += [{"episode": 10 + k, "n_sv": 0, "outcome": "success", "wall_s": 0.5 * k} for k in range(1, 11)]
    assert training_wall_s(recs) == (25.0, 2)
    s = summary(recs)
    assert s["wall_s"] == 25.0 and s["segments"] == 2 and s["episodes_per_s"] == pytest.approx(20 / 25)
    assert training_wall_s(recs[:10]) == (20.0, 1)
    assert training_wall_s([{"episode": 1}])[1] == 0


# --- the NMPC a policy was trained with: recorded, checked on resume / init, evaluation's default ---

UNBOUNDED = "bimacppo_mpc/bimacppo_mpc/config/mpc_unbounded.yaml"


@pytest.fixture(scope="module")
def trained_unbounded(trained):
    from conftest import REPO

    d, cfg, _ = trained
    run = d / "run_unbounded"
    rc = train_main(["--episodes", "2", "--seed", "3", "--run-dir", str(run), "--ppo-config", str(cfg),
                     "--no-progress", "--mpc-config", str(REPO / UNBOUNDED)])
    assert rc == 0
    return run


def test_train_records_its_mpc_config_in_checkpoint_policy_and_run_json(trained_unbounded, trained):
    from bimacppo_mpc import MPCConfig
    from conftest import REPO

    from bimacppo_learning.checkpoint import load_checkpoint, mpc_config_of, run_meta_of
    from bimacppo_planner.agent import load_policy

    run = trained_unbounded
    unbounded = MPCConfig.load(REPO / UNBOUNDED)
    assert unbounded.to_dict() != MPCConfig.load().to_dict()       # the test means something
    ckpt = sorted((run / "checkpoints").glob("*.pt"))[-1]
    meta = run_meta_of(load_checkpoint(ckpt), ckpt)
    assert meta["mpc_config"] == unbounded.to_dict()
    assert mpc_config_of(meta, ckpt).to_dict() == unbounded.to_dict()
    assert load_policy(run / "policy.pt").meta["mpc_config"] == unbounded.to_dict()
    assert json.loads((run / "run.json").read_text())["mpc_config"] == unbounded.to_dict()
    # a run without --mpc-config records the packaged controller
    _, _, packaged_run = trained
    assert load_policy(packaged_run / "policy.pt").meta["mpc_config"] == MPCConfig.load().to_dict()


def test_resume_with_another_mpc_config_is_refused_naming_a_field(trained_unbounded, tmp_path, capsys):
    from bimacppo_mpc import MPCConfig

    run = trained_unbounded
    before = _snapshot(run)
    cfg = run.parent / "ppo.yaml"
    horizon = tmp_path / "mpc_h12.yaml"
    horizon.write_text("horizon: 12\n")
    packaged = MPCConfig.load()
    for extra, says in ((["--mpc-config", str(horizon)], f"horizon: {packaged.horizon} != 12"),
                        ([], f"steer_rate_max: None != {packaged.steer_rate_max}")):
        rc = train_main(["--episodes", "4", "--seed", "3", "--run-dir", str(run), "--ppo-config", str(cfg),
                         "--no-progress", "--resume", *extra])
        assert rc == 2, extra
        line = _one_error_line(capsys.readouterr().err, "bimacppo-train")
        assert "another MPC config" in line and says in line and "--mpc-config" in line, line
    assert _snapshot(run) == before
    bad = tmp_path / "mpc_bad.yaml"
    bad.write_text("horizonn: 12\n")
    assert train_main(["--episodes", "2", "--run-dir", str(tmp_path / "r"), "--mpc-config", str(bad)]) == 2
    assert "horizonn" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert not (tmp_path / "r").exists()


def test_a_checkpoint_without_a_recorded_mpc_config_is_not_compared_but_warned_about(trained_unbounded, caplog):
    from bimacppo_mpc import MPCConfig

    from bimacppo_learning.checkpoint import load_checkpoint, run_meta_of
    from bimacppo_learning.cli import check_checkpoint_fits
    from bimacppo_planner.decision import EnvConfig

    ckpt = sorted((trained_unbounded / "checkpoints").glob("*.pt"))[-1]
    d = load_checkpoint(ckpt)
    meta = run_meta_of(d, ckpt)
    old = {k: v for k, v in meta.items() if k != "mpc_config"}     # written before runs recorded it
    dims = (d["agent"]["obs_dim"], d["agent"]["nvec"])
    with caplog.at_level("WARNING"):
        assert check_checkpoint_fits(ckpt, *dims, old, EnvConfig.load(), MPCConfig.load()) is None
    assert any("records no MPC config" in r.getMessage() for r in caplog.records)
    # the recorded one is compared: the same passes, another is named
    assert check_checkpoint_fits(ckpt, *dims, meta, EnvConfig.load(), MPCConfig.from_dict(meta["mpc_config"])) is None
    why = check_checkpoint_fits(ckpt, *dims, meta, EnvConfig.load(), MPCConfig.load())
    assert "another MPC config" in why and "jerk_max: None != " in why
    broken = {**meta, "mpc_config": {**meta["mpc_config"], "horizon": -1}}
    assert "run metadata mpc_config: key 'horizon'" in check_checkpoint_fits(ckpt, *dims, broken, EnvConfig.load(),
                                                                              MPCConfig.load())


def test_evaluation_defaults_to_the_recorded_mpc_config(trained_unbounded, tmp_path, capsys):
    from bimacppo_mpc import MPCConfig
    from bimacppo_mpc.config import DEFAULT_PATH
    from conftest import REPO

    from bimacppo_learning.evaluate import resolve_mpc_config, resolve_policy

    unbounded = MPCConfig.load(REPO / UNBOUNDED)
    for f in ("policy.pt", sorted((trained_unbounded / "checkpoints").glob("*.pt"))[-1].relative_to(trained_unbounded)):
        _, loaded, _ = resolve_policy(trained_unbounded / f)
        assert resolve_mpc_config(loaded).to_dict() == unbounded.to_dict(), f
        other = tmp_path / "mpc.yaml"
        other.write_text("horizon: 12\n")
        assert resolve_mpc_config(loaded, other).horizon == 12           # --mpc-config wins
    # a file that records none (the clone, written before runs recorded theirs): the packaged
    # mpc.yaml (None); a policy trained before the second-start cut existed records no cut key,
    # and that means the packaged bounded controller without the cut; the shipped default was
    # trained with mpc_uncut.yaml and records it key for key
    from bimacppo_mpc.config import CONFIG_DIR
    _, clone, _ = resolve_policy(REPO / "bimacppo_planner/bimacppo_planner/policies/bimacppo_dual_lane_clone.pt")
    assert "mpc_config" not in clone.meta and resolve_mpc_config(clone) is None
    uncut = MPCConfig.load(CONFIG_DIR / "mpc_uncut.yaml").to_dict()
    _, before_cut, _ = resolve_policy(REPO / "studies/policies/bimacppo_dual_lane_standing5000.pt")
    assert "second_start_cut" not in before_cut.meta["mpc_config"]["fast"]
    assert resolve_mpc_config(before_cut).to_dict() == uncut
    _, shipped, _ = resolve_policy(None)
    assert shipped.meta["mpc_config"]["fast"]["second_start_cut"] is None
    assert resolve_mpc_config(shipped).to_dict() == uncut
    # the table says which controller ran: the record, a --mpc-config, or the packaged one
    common = ["--episodes", "1", "--n-sv", "0", "--tasks", "straight", "--workers", "1", "--no-random-row"]
    for extra, says in (([], "(run mpc_config) (fast.second_start_cut: None, fast.steer_bound_other_side: False)"),
                        (["--mpc-config", str(DEFAULT_PATH)],
                         f"NMPC: {DEFAULT_PATH} (fast.second_start_cut: 2.0, fast.steer_bound_other_side: True)"),
                        ([str(REPO / "bimacppo_planner/bimacppo_planner/policies/bimacppo_dual_lane_clone.pt")],
                         "(packaged; the policy records none)")):
        assert evaluate_main([*extra, *common]) == 0
        assert says in capsys.readouterr().out, extra
    # end to end: a policy file's cells run its recorded controller unless told otherwise
    from bimacppo_learning.evaluate import evaluate

    kw = dict(map_id="dual_lane_4way", n_svs=[0], tasks=[1], episodes=1, workers=1, random_row=False)
    pol = trained_unbounded / "policy.pt"
    default, explicit = evaluate(pol, **kw)[0], evaluate(pol, mpc_config=REPO / UNBOUNDED, **kw)[0]
    packaged = evaluate(pol, mpc_config=DEFAULT_PATH, **kw)[0]
    assert (default.comfort.ticks, default.comfort.jerk_sq) == (explicit.comfort.ticks, explicit.comfort.jerk_sq)
    assert (default.comfort.ticks, default.comfort.jerk_sq) != (packaged.comfort.ticks, packaged.comfort.jerk_sq)


def test_train_world_config_sets_the_training_episodes_only_and_is_recorded(trained, tmp_path, capsys):
    from bimacppo_learning.cli import make_env
    from bimacppo_planner.decision import EnvConfig
    from bimacppo_planner.policy import Policy
    from bimacppo_sim import WorldConfig

    _, cfg, _ = trained
    world = tmp_path / "world.yaml"
    world.write_text("ev_speed_min: 0.0\nev_speed_max: 0.5\n")
    out = tmp_path / "standing"
    assert train_main(["--episodes", "2", "--seed", "3", "--run-dir", str(out), "--ppo-config", str(cfg),
                       "--world-config", str(world), "--no-progress"]) == 0
    assert json.loads((out / "run.json").read_text())["world_config"]["ev_speed_max"] == 0.5
    assert Policy.load(out / "policy.pt").meta["world_config"]["ev_speed_min"] == 0.0
    starts = []
    for wc in (WorldConfig.load(world), None):
        env = make_env("dual_lane_4way", EnvConfig.load(), "fast", world_config=wc)()
        env.reset(options={"n_sv": 0, "task": "straight", "scenario_seed": 4})
        starts.append(float(env.world.ego[2]))
    assert starts[0] <= 0.5 and starts[1] >= 3.0          # the file's speeds, else the packaged 3-6 m/s
    # a resume in another world than the run's, or in the packaged one, is refused before writing
    before = _snapshot(out)
    for extra in (["--world-config", str(tmp_path / "other.yaml")], []):
        (tmp_path / "other.yaml").write_text("ev_speed_min: 0.0\nev_speed_max: 0.7\n")
        assert train_main(["--episodes", "3", "--seed", "3", "--run-dir", str(out), "--ppo-config", str(cfg),
                           "--resume", "--no-progress", *extra]) == 2
        line = _one_error_line(capsys.readouterr().err, "bimacppo-train")
        assert "another world" in line and "ev_speed_max: 0.5 != " in line, line
    assert _snapshot(out) == before
    assert train_main(["--episodes", "3", "--seed", "3", "--run-dir", str(out), "--ppo-config", str(cfg),
                       "--resume", "--no-progress", "--world-config", str(world)]) == 0
    world.write_text("ev_sped_min: 0.0\n")
    assert train_main(["--episodes", "2", "--run-dir", str(tmp_path / "bad"), "--world-config", str(world)]) == 2
    assert "ev_sped_min" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert not (tmp_path / "bad").exists()


def test_the_standing_starts_study_overlay_changes_only_the_start_speed():
    from conftest import REPO
    from bimacppo_common import config as common_config
    from bimacppo_sim import WorldConfig

    packaged = common_config.to_dict(WorldConfig.load())
    standing = common_config.to_dict(WorldConfig.load(REPO / "studies" / "config" / "world_standing_starts.yaml"))
    assert {k for k in packaged if packaged[k] != standing[k]} == {"ev_speed_min"}
    assert standing["ev_speed_min"] == 0.0 < packaged["ev_speed_min"]


def test_a_fine_tune_may_add_observation_features_only_when_told(trained, tmp_path, env_yaml, capsys):
    """Turning a feature group on (observation.lanes) changes the input size: refused for
    --init-policy without --fine-tune-observation; with it the run starts from the checkpoint's
    agent widened by zero-weight inputs and records the new observation. The flag adds groups
    only: another value of a shared key, or a group the checkpoint has and the run leaves out,
    is refused with the key named, and the run directory is not created."""
    import torch

    from bimacppo_learning.checkpoint import load_checkpoint

    cfg, run, base = _fine_tune_args(trained)
    lanes = env_yaml("observation:\n  lanes: true\n")
    out = tmp_path / "lanes"
    assert train_main([*base, "--run-dir", str(out), "--env-config", str(lanes)]) == 2
    assert "observations of size 16" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert not out.exists()
    both = env_yaml("observation:\n  lanes: true\n  sv_clip: 30.0\n")
    assert train_main([*base, "--run-dir", str(out), "--env-config", str(both), "--fine-tune-observation"]) == 2
    line = _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert "observation.sv_clip: 7.5 != 30.0" in line and not out.exists()
    assert train_main(["--episodes", "2", "--run-dir", str(tmp_path / "x"), "--fine-tune-observation"]) == 2
    assert "needs --init-policy" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert train_main([*base, "--run-dir", str(out), "--env-config", str(lanes), "--fine-tune-observation"]) == 0
    assert json.loads((out / "run.json").read_text())["env_config"]["observation"]["lanes"] is True
    src = load_checkpoint(sorted((run / "checkpoints").glob("*.pt"))[-1])["agent"]
    tuned = load_checkpoint(sorted((out / "checkpoints").glob("*.pt"))[-1])["agent"]
    assert tuned["obs_dim"] == 18
    w_src, w_new = src["actor"]["0.weight"], tuned["actor"]["0.weight"]
    assert w_new.shape == (w_src.shape[0], 18)
    assert not torch.equal(w_new[:, :16], w_src)            # trained two episodes from the checkpoint
    # and the widened run cannot be continued from, or fine-tuned back to, the checkpoint's observation
    back = tmp_path / "back"
    newest = sorted((out / "checkpoints").glob("*.pt"))[-1]
    assert train_main(["--episodes", "2", "--ppo-config", str(cfg), "--no-progress", "--init-policy", str(newest),
                       "--run-dir", str(back), "--fine-tune-observation"]) == 2
    line = _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert "leaves out the checkpoint's lanes features" in line and not back.exists()


def test_a_fine_tune_can_start_its_lane_change_head_from_a_keep_prior(trained, tmp_path, capsys):
    """--fine-tune-lane-prior P: the fine-tune's agent keeps the lane with probability P in every
    state (left and right share the rest) while its other heads act as the source's do; the flag
    needs --init-policy and a probability strictly between 0 and 1, refused on one line before
    anything is written."""
    import numpy as np
    import torch

    from bimacppo_learning.cli import _preflight, _train_parser
    from bimacppo_learning.ppo_config import load_config
    from bimacppo_learning.trainer import load_agent
    from bimacppo_mpc import MPCConfig
    from bimacppo_planner.decision import LANE_CHANGE_HEAD, EnvConfig

    cfg, run, base = _fine_tune_args(trained)
    ckpt = base[-1]
    args = _train_parser().parse_args([*base, "--fine-tune-lane-prior", "0.9", "--run-dir", str(tmp_path / "p")])
    pcfg, _ = load_config(cfg)
    why, agent, _, _ = _preflight(args, EnvConfig.load(), pcfg, tmp_path / "p", MPCConfig.load())
    assert why is None
    source = load_agent(ckpt)
    obs = torch.from_numpy(np.random.default_rng(0).normal(0.0, 3.0, size=(20, agent.obs_dim)).astype(np.float32))
    with torch.no_grad():
        tuned, orig = agent.dist(obs).log_probs, source.dist(obs).log_probs
    probs = tuned[LANE_CHANGE_HEAD].exp().numpy()
    assert np.allclose(probs, [[0.05, 0.9, 0.05]] * 20, atol=1e-6)
    assert not np.allclose(orig[LANE_CHANGE_HEAD].exp().numpy(), probs, atol=1e-3)   # the source's head differs
    for head in range(len(tuned)):
        if head != LANE_CHANGE_HEAD:
            assert torch.allclose(tuned[head], orig[head])
    out = tmp_path / "run"
    assert train_main([*base, "--fine-tune-lane-prior", "0.9", "--run-dir", str(out)]) == 0
    assert "--fine-tune-lane-prior" in json.loads((out / "run.json").read_text())["argv"]
    capsys.readouterr()
    for bad in ("0", "1", "1.5", "nan"):
        assert train_main([*base, "--fine-tune-lane-prior", bad, "--run-dir", str(tmp_path / "bad")]) == 2
        assert "probability in (0, 1)" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert train_main(["--episodes", "2", "--fine-tune-lane-prior", "0.9", "--run-dir", str(tmp_path / "bad")]) == 2
    assert "needs --init-policy" in _one_error_line(capsys.readouterr().err, "bimacppo-train")
    assert not (tmp_path / "bad").exists()


def test_train_prints_its_cpu_time_split_like_its_wall_time(tmp_path, capsys):
    import re

    cfg = tmp_path / "ppo.yaml"
    cfg.write_text(SMALL.replace("num_envs: 1", "num_envs: 2").replace("vector: sync", "vector: batched")
                   .replace("rollout_steps: 128", "rollout_steps: 32").replace("tensorboard: true", "tensorboard: false"))
    rc = train_main(["--episodes", "3", "--seed", "1", "--run-dir", str(tmp_path / "run"), "--ppo-config", str(cfg),
                     "--no-progress"])
    assert rc == 0
    out = capsys.readouterr().out
    m = re.search(r"^CPU: ([\d.]+) s = env ([\d.]+) \(NMPC ([\d.]+)\) \+ policy ([\d.]+) \+ PPO update ([\d.]+) \+ "
                  r"bookkeeping (-?[\d.]+) \(this process, every thread\)$", out, re.M)
    assert m, out
    total, env, nmpc, policy, update, other = map(float, m.groups())
    # the NMPC runs inside env stepping, and the loop's CPU is the sum of its parts (to the print's rounding)
    assert 0.0 < nmpc <= env + 0.1 and policy >= 0.0 and update >= 0.0
    assert total == pytest.approx(env + policy + update + other, abs=0.25) and other >= -0.1
