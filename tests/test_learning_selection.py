"""bimacppo-select: a run's checkpoints compared on validation seeds, the best one written."""
import pathlib

import pytest
import torch

from bimacppo_learning import evaluate as evaluate_mod
from bimacppo_learning.cli import train_main
from bimacppo_learning.selection import Candidate, choose, main
from bimacppo_planner.policy import Policy

SMALL = """
ppo:
  minibatch_size: 64
  epochs: 2
train:
  num_envs: 1
  vector: sync
  rollout_steps: 64
  checkpoint_every: 1
  keep_checkpoints: 10
  tensorboard: false
  progress_bar: false
"""


def cand(name, episodes, cells):
    return Candidate(pathlib.Path(name), episodes, dict(cells))


def test_worst_cell_and_mean_criteria_rank_differently_and_ties_go_to_more_training():
    steady = cand("a", 100, {(0, 3): 90.0, (1, 3): 90.0, (2, 3): 90.0})     # mean 90, worst 90
    spiky = cand("b", 200, {(0, 3): 100.0, (1, 3): 100.0, (2, 3): 80.0})    # mean 93.3, worst 80
    assert choose([steady, spiky], "worst-cell") is steady
    assert choose([steady, spiky], "mean") is spiky
    later = cand("c", 300, steady.success)
    assert choose([steady, spiky, later], "worst-cell") is later
    better_mean = cand("d", 50, {(0, 3): 90.0, (1, 3): 95.0, (2, 3): 90.0})
    assert choose([steady, better_mean, later], "worst-cell") is better_mean


def test_choose_refuses_nothing_and_candidates_scored_on_other_cells():
    with pytest.raises(ValueError, match="no checkpoints"):
        choose([])
    with pytest.raises(ValueError, match="other cells"):
        choose([cand("a", 1, {(0, 3): 1.0}), cand("b", 2, {(1, 3): 1.0})])
    with pytest.raises(ValueError, match="criterion"):
        choose([cand("a", 1, {(0, 3): 1.0})], "median")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("select")
    cfg = d / "ppo.yaml"
    cfg.write_text(SMALL)
    rc = train_main(["--episodes", "3", "--seed", "4", "--run-dir", str(d / "run"), "--ppo-config", str(cfg),
                     "--no-progress"])
    assert rc == 0
    ckpts = sorted((d / "run" / "checkpoints").glob("ckpt_ep*.pt"))
    assert len(ckpts) >= 2, ckpts
    return d / "run"


CELLS = ["--episodes", "1", "--n-sv", "0", "--tasks", "straight", "--workers", "1"]


def test_select_chooses_on_the_second_validation_set_when_told_and_never_on_a_test_set(run, tmp_path, monkeypatch,
                                                                                          capsys):
    """--seed-set validation2 evaluates every checkpoint on the second pair's validation set and
    records it; a test set is not a choice the parser offers (exit 2, nothing written), nor one
    score_checkpoints accepts."""
    from bimacppo_learning.selection import score_checkpoints

    seen = []
    real = evaluate_mod.evaluate

    def spy(*a, **kw):
        seen.append(kw["seed_set"])
        return real(*a, **kw)

    monkeypatch.setattr(evaluate_mod, "evaluate", spy)
    out = tmp_path / "chosen2.pt"
    assert main([str(run), str(out), *CELLS, "--seed-set", "validation2"]) == 0
    assert seen and set(seen) == {"validation2"}
    assert Policy.load(out).meta["chosen_on_validation"]["seed_set"] == "validation2"
    for name in ("test", "test2"):
        with pytest.raises(SystemExit) as e:
            main([str(run), str(tmp_path / f"{name}.pt"), *CELLS, "--seed-set", name])
        assert e.value.code == 2 and not (tmp_path / f"{name}.pt").exists()
        with pytest.raises(ValueError, match="only reports"):
            score_checkpoints([], n_svs=[0], tasks=[1], episodes=1, seed_set=name)


def test_select_writes_the_chosen_checkpoint_as_a_policy_on_validation_seeds_only(run, tmp_path, monkeypatch,
                                                                                   capsys):
    seen = []
    real = evaluate_mod.evaluate

    def spy(*a, **kw):
        seen.append((a[0], kw["seed_set"]))
        return real(*a, **kw)

    monkeypatch.setattr(evaluate_mod, "evaluate", spy)
    out = tmp_path / "chosen.pt"
    assert main([str(run), str(out), *CELLS, "--table", str(tmp_path / "sel")]) == 0
    ckpts = sorted((run / "checkpoints").glob("ckpt_ep*.pt"))
    assert [s for _, s in seen] == ["validation"] * len(ckpts)
    assert sorted(pathlib.Path(p).name for p, _ in seen) == [p.name for p in ckpts]

    pol = Policy.load(out)
    record = pol.meta["chosen_on_validation"]
    assert pol.selection == "median" and record["seed_set"] == "validation"
    assert record["candidates"] == len(ckpts) and record["criterion"] == "worst-cell"
    src = torch.load(run / "checkpoints" / record["checkpoint"], weights_only=True)
    written = torch.load(out, weights_only=True)
    for k, v in src["agent"]["actor"].items():
        assert torch.equal(written["actor"][k], v)
    assert pol.meta["env_config"] == Policy.load(run / "policy.pt").meta["env_config"]
    text = capsys.readouterr().out
    assert "**chosen**" in text and f"chose {record['checkpoint']}" in text
    rows = (tmp_path / "sel.csv").read_text().splitlines()
    assert rows[0] == "checkpoint,episodes,task,n_sv,success_pct" and len(rows) == 1 + len(ckpts)
    assert (tmp_path / "sel.md").is_file() and (tmp_path / "sel.png").stat().st_size > 0


def test_select_refusals_are_one_line_and_write_nothing(run, tmp_path, capsys):
    out = tmp_path / "x.pt"
    out.write_bytes(b"keep me")
    assert main([str(run), str(out), *CELLS]) == 2
    assert out.read_bytes() == b"keep me"
    assert main([str(tmp_path), str(tmp_path / "y.pt"), *CELLS]) == 2          # no checkpoints/
    assert main([str(run), str(tmp_path / "y.pt"), *CELLS, "--from-episodes", "999999"]) == 2
    bad = tmp_path / "bad_run"
    (bad / "checkpoints").mkdir(parents=True)
    (bad / "checkpoints" / "ckpt_ep00000005.pt").write_bytes(b"not a checkpoint")
    assert main([str(bad), str(tmp_path / "y.pt"), *CELLS]) == 2
    assert main([str(run), str(tmp_path / "y.pt"), *CELLS, "--n-sv", "7"]) == 2
    assert not (tmp_path / "y.pt").exists()
    errors = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(errors) == 5 and all(ln.startswith("bimacppo-select: error: ") for ln in errors), errors
    assert "exists" in errors[0] and "checkpoints/" in errors[1] and "999999" in errors[2]
    assert "ckpt_ep00000005.pt" in errors[3] and "N_sv=7" in errors[4]


def test_select_runs_the_overtaking_protocol_and_records_it(run, tmp_path):
    out = tmp_path / "overtake.pt"
    assert main([str(run), str(out), "--episodes", "1", "--map", "three_lane_straight", "--tasks", "straight",
                 "--n-sv", "3", "--slow-svs", "2", "--workers", "1", "--action", "argmax"]) == 0
    pol = Policy.load(out)
    record = pol.meta["chosen_on_validation"]
    assert pol.selection == "argmax"
    assert (record["map"], record["tasks"], record["n_sv"], record["slow_svs"]) == ("three_lane_straight",
                                                                                   ["straight"], [3], 2)
    assert main([str(run), str(tmp_path / "n.pt"), "--episodes", "1", "--slow-svs", "-1"]) == 2


def test_the_checkpoint_keeping_overlay_changes_only_the_checkpoint_cadence():
    import dataclasses

    from bimacppo_learning.ppo_config import load_config

    from conftest import REPO

    ppo, train = load_config()
    ppo2, train2 = load_config(REPO / "studies" / "config" / "ppo_checkpoints250.yaml")
    assert ppo2 == ppo
    assert (train2.checkpoint_every, train2.keep_checkpoints) == (250, 25)
    assert dataclasses.replace(train2, checkpoint_every=train.checkpoint_every,
                               keep_checkpoints=train.keep_checkpoints) == train
    assert train2.checkpoint_every * train2.keep_checkpoints >= 5000   # a 5,000-episode run keeps them all
