"""bimacppo-experiments through a local Ray: the pipeline end to end on tiny budgets, a small
grid with one broken run, skip / resume / caching, and the report on partial results."""
import json
import os
import time

import pytest
import yaml

from bimacppo_learning import experiments as ex

PPO_TINY = """
ppo:
  minibatch_size: 64
  epochs: 2
train:
  num_envs: 1
  batch_workers: 1
  vector: sync
  rollout_steps: 64
  checkpoint_every: 2
  tensorboard: false
  progress_bar: false
"""


def _write_config(d, name="exp.yaml", **extra):
    (d / "ppo.yaml").write_text(PPO_TINY)
    doc = {
        "methods": ["bimab", "random"], "seeds": [0], "episodes": 4,
        "runs_dir": str(d / "runs"), "results_md": str(d / "docs" / "results.md"),
        "img_prefix": str(d / "docs" / "img" / "exp"),
        "train": {"num_envs": 1, "vector": "sync", "ppo_config": str(d / "ppo.yaml"), "poll_s": 0.2,
                  "num_cpus": 1},
        "evaluation": {"episodes": 1, "n_sv": [0, 1], "tasks": ["left"], "workers": 1, "reference_drivers": ["go"],
                       "num_cpus": 1},
        "overtake": {"episodes": 2, "test_episodes": 2, "test_n_sv": 2},
        "report": {"window": 2},
    }
    for k, v in extra.items():
        doc[k] = {**doc[k], **v} if isinstance(v, dict) else v
    p = d / name

    p.write_text(yaml.safe_dump(doc))
    return p


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray for the module (starting one takes seconds); every step finds it
    initialised, uses it and leaves it running."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


# --- end to end ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pipeline(local_ray, tmp_path_factory):
    d = tmp_path_factory.mktemp("exp")
    cfg_path = _write_config(d)
    assert ex.main(["--config", str(cfg_path), "all"]) == 0
    return d, cfg_path, ex.load_experiment_config(cfg_path)


# --- end to end ---------------------------------------------------------------------------


def test_all_trains_evaluates_finetunes_and_reports(pipeline):
    d, _, cfg = pipeline
    for m in ("bimab", "random"):
        run = cfg.run_dir(m, 0)
        assert [r["episode"] for r in ex.read_history(run)] == [1, 2, 3, 4]
        assert json.loads((run / "run.json").read_text())["curriculum"] == m
        for map_id in ("dual_lane_4way", "single_lane_4way"):
            cells = ex.read_eval_csv(cfg.eval_prefix(run, map_id).with_suffix(".csv"))
            assert set(cells) == {(0, 0), (0, 1)} and all(v[3] == 1 for v in cells.values())
    for map_id in ("dual_lane_4way", "single_lane_4way"):
        assert ex.read_eval_csv(cfg.reference_prefix("go", map_id).with_suffix(".csv"))
    test = json.loads((cfg.overtake_dir(0) / "test.json").read_text())
    assert test["episodes"] == 2 and test["n_sv"] == 2
    assert sum(test["n_slow_counts"].values()) == 2 and all(0 <= int(k) <= 2 for k in test["n_slow_counts"])
    assert abs(test["success_pct"] + test["collision_pct"] + test["timeout_pct"] - 100.0) < 1e-9
    assert ex.last_episode(cfg.overtake_dir(0)) == 2
    text = (d / "docs" / "results.md").read_text()
    for needle in ("Table II", "Table III", "Table I", "| BiM-ACPPO | left |", "| Random CPPO | left |",
                   '| scripted "go" | left |', "| random policy | left |", "Nothing: every run", "IQM [95 % CI]"):
        assert needle in text
    # the rliable rows: every method and driver, BiM-ACPPO's improvement over each other row
    agg = [ln for ln in text.splitlines() if ln.startswith("| ") and ln.count("[") >= 2]
    assert any(ln.startswith("| Random CPPO | 1 |") and ln.rstrip(" |").endswith("]") for ln in agg), agg
    assert any(ln.startswith("| BiM-ACPPO | 1 |") and ln.endswith("| – |") for ln in agg), agg
    assert any(ln.startswith("| random policy | 1 |") for ln in agg), agg
    for name in ("fig5_clusters", "fig6_arms", "success"):
        assert (d / "docs" / "img" / f"exp_{name}.png").is_file()


def test_train_skips_finished_runs(pipeline):
    _, _, cfg = pipeline
    hist = cfg.run_dir("bimab", 0) / "history.jsonl"
    before = hist.stat().st_mtime_ns
    said = []
    assert ex.train(cfg, echo=said.append) == 0
    assert hist.stat().st_mtime_ns == before
    assert len(said) == 2 and all("skipped" in s for s in said)


def test_evaluate_uses_cache_until_the_policy_changes(pipeline):
    _, _, cfg = pipeline
    said = []
    ex.evaluate_all(cfg, echo=said.append)
    assert said and all("cached" in s for s in said)
    policy = cfg.run_dir("random", 0) / "policy.pt"
    # newer than every CSV the fixture wrote (its evaluation can take > 10 s after training
    # on a loaded machine, so "policy mtime + 10 s" is not enough)
    t = time.time() + 10
    os.utime(policy, (t, t))
    said.clear()
    ex.evaluate_all(cfg, echo=said.append)
    wrote = [s for s in said if "wrote" in s]
    assert len(wrote) == 2 and all(s.startswith("random-s0") for s in wrote)


def test_train_resumes_an_unfinished_run(pipeline, tmp_path):
    _, cfg_path, _ = pipeline
    cfg = ex.load_experiment_config(cfg_path, overrides={"episodes": 6, "methods": ["random"]})
    assert ex.run_status(cfg, "random", 0).state == "partial"
    said = []
    assert ex.train(cfg, echo=said.append) == 0
    assert [r["episode"] for r in ex.read_history(cfg.run_dir("random", 0))] == list(range(1, 7))
    assert "--resume" in (cfg.run_dir("random", 0) / "train.log").read_text()
    assert any(s.startswith("random-s0: resumed to 6") for s in said), said


def test_report_on_partial_results_lists_what_is_missing(pipeline, tmp_path):
    _, cfg_path, _ = pipeline
    cfg = ex.load_experiment_config(cfg_path, overrides={
        "methods": ["bimab", "fixed"], "seeds": [0, 1], "results_md": str(tmp_path / "r.md"),
        "img_prefix": str(tmp_path / "img" / "x")})
    res = ex.report(cfg)
    text = (tmp_path / "r.md").read_text()
    assert any("fixed-s0" in m for m in res["missing"]) and any("bimab-s1" in m for m in res["missing"])
    assert "`fixed-s0`" in text and "`bimab-s1`" in text
    assert "| BiM-ACPPO | left |" in text and "| Fixed PPO | left |" not in text
    assert "Nothing: every run" not in text


# --- a grid with a broken run ------------------------------------------------------------


def _mtimes(run):
    return {p.name: p.stat().st_mtime_ns for p in [*(run / "checkpoints").iterdir(), run / "policy.pt",
                                                   run / "history.jsonl", run / "eval_dual_lane_4way.csv"]}


def test_grid_runs_in_parallel_reports_the_broken_run_and_redoes_nothing(local_ray, tmp_path, capsys):
    """2 methods x 2 seeds; random-s1 holds a corrupt checkpoint (a run killed while a disk
    failed), so its resume fails: it is reported with its log and the other three finish."""
    cfg_path = _write_config(tmp_path, seeds=[0, 1], episodes=3, zero_shot_map=None,
                             evaluation={"n_sv": [0], "reference_drivers": []})
    cfg = ex.load_experiment_config(cfg_path)
    broken = cfg.run_dir("random", 1)
    (broken / "checkpoints").mkdir(parents=True)
    (broken / "checkpoints" / "ckpt_ep00000002.pt").write_bytes(b"not a checkpoint")
    good = [cfg.run_dir(m, s) for m in ("bimab", "random") for s in (0, 1) if (m, s) != ("random", 1)]

    assert ex.main(["--config", str(cfg_path), "train"]) == 1
    out = capsys.readouterr().out
    fail = [ln for ln in out.splitlines() if ln.startswith("random-s1: FAILED")]
    assert len(fail) == 1 and "ckpt_ep00000002.pt: not a readable torch file" in fail[0] and f"(log: {broken / 'train.log'})" in fail[0]
    assert "bimacppo-train: error:" in (broken / "train.log").read_text()
    assert "training: done 3, running 0, queued 0, failed 1 (of 4)" in out
    assert "running 2" in out                                     # two 1-CPU runs at once on 2 CPUs
    for run in good:
        assert [r["episode"] for r in ex.read_history(run)] == [1, 2, 3] and (run / "policy.pt").is_file()
        assert json.loads((run / "experiment.json").read_text())["curriculum"] == run.name.split("-")[0]
        assert "$ bimacppo-train --curriculum" in (run / "train.log").read_text()

    assert ex.main(["--config", str(cfg_path), "evaluate"]) == 0
    out = capsys.readouterr().out
    assert "random-s1 (partial, 0/3 episodes)" in out
    for run in good:
        assert set(ex.read_eval_csv(run / "eval_dual_lane_4way.csv")) == {(0, 0)}
    before = {run: _mtimes(run) for run in good}

    assert ex.main(["--config", str(cfg_path), "train"]) == 1     # still broken, nothing else redone
    assert ex.main(["--config", str(cfg_path), "evaluate"]) == 0
    out = capsys.readouterr().out
    assert sum("done (3 episodes), skipped" in ln for ln in out.splitlines()) == 3
    assert sum(": cached " in ln for ln in out.splitlines()) == 3
    assert "training: done 0, running 0, queued 0, failed 1 (of 1)" in out
    assert {run: _mtimes(run) for run in good} == before
