"""bimacppo-experiments: the pipeline end to end on tiny budgets, skip/resume/caching, the
aggregation maths on synthetic data, the report on partial results, errors, and the env's
n_slow option the overtaking fine-tune relies on."""
import json
import os
import time

import numpy as np
import pytest

from bimacppo_learning import experiments as ex
from bimacppo_learning.evaluate import CellResult, write_outputs

PPO_TINY = """
ppo:
  minibatch_size: 64
  epochs: 2
train:
  num_envs: 1
  vector: sync
  rollout_steps: 64
  checkpoint_every: 2
  tensorboard: false
  progress_bar: false
"""


def _write_config(d, **extra):
    (d / "ppo.yaml").write_text(PPO_TINY)
    doc = {
        "methods": ["bimab", "random"], "seeds": [0], "episodes": 4,
        "runs_dir": str(d / "runs"), "results_md": str(d / "docs" / "results.md"),
        "img_prefix": str(d / "docs" / "img" / "exp"),
        "train": {"num_envs": 1, "vector": "sync", "ppo_config": str(d / "ppo.yaml"), "poll_s": 0.2},
        "evaluation": {"episodes": 1, "n_sv": [0, 1], "tasks": ["left"], "workers": 1, "reference_drivers": ["go"]},
        "overtake": {"episodes": 2, "test_episodes": 2, "test_n_sv": 2},
        "report": {"window": 2},
    }
    for k, v in extra.items():
        doc[k] = {**doc[k], **v} if isinstance(v, dict) else v
    p = d / "exp.yaml"
    import yaml

    p.write_text(yaml.safe_dump(doc))
    return p


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
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
                   '| scripted "go" | left |', "Nothing: every run"):
        assert needle in text
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
    assert "resumed to 6" in said[0]


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


# --- errors ------------------------------------------------------------------------------


def test_unknown_method_is_an_error(pipeline, capsys):
    _, cfg_path, cfg = pipeline
    with pytest.raises(ex.ExperimentError, match="unknown method.*'ppo'"):
        ex.train(cfg, only=["ppo"])
    assert ex.main(["--config", str(cfg_path), "train", "--only", "ppo"]) == 2
    assert "unknown method" in capsys.readouterr().err


@pytest.mark.parametrize("doc, key", [
    ("bogus: 1\n", "bogus"),
    ("episodes: many\n", "episodes"),
    ("episodes: 0\n", "episodes"),
    ("methods: [bimab, ppo]\n", "methods"),
    ("evaluation: {episodes: 5000}\n", "evaluation.episodes"),
    ("overtake: {speed: 3}\n", "overtake.speed"),
    ("report: {efficiency_fraction: 1.5}\n", "report.efficiency_fraction"),
])
def test_config_errors_name_file_and_key(tmp_path, doc, key):
    p = tmp_path / "bad.yaml"
    p.write_text(doc)
    with pytest.raises(ex.ExperimentError) as ei:
        ex.load_experiment_config(p)
    assert str(p) in str(ei.value) and f"'{key}'" in str(ei.value)


def test_env_config_reaches_bimacppo_train_and_a_missing_one_is_named(tmp_path):
    env = tmp_path / "env.yaml"
    env.write_text("action: {decision_every: 3}\n")
    ok = tmp_path / "ok.yaml"
    ok.write_text(f"train: {{env_config: {env}}}\n")
    argv = ex.train_argv(ex.load_experiment_config(ok), "bimab", 0, resume=False)
    assert argv[argv.index("--env-config") + 1] == str(env)
    assert "--env-config" not in ex.train_argv(ex.load_experiment_config(), "bimab", 0, resume=False)
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"train: {{env_config: {tmp_path / 'nope.yaml'}}}\n")
    with pytest.raises(ex.ExperimentError, match=r"train.env_config.*no such file.*nope.yaml"):
        ex.load_experiment_config(bad)


def test_packaged_config_is_the_papers_grid():
    cfg = ex.load_experiment_config()
    assert set(cfg.methods) == set(ex.CURRICULA) and len(cfg.seeds) >= 3
    assert cfg.evaluation.episodes == 100 and cfg.overtake.test_episodes == 100


def test_corrupt_history_is_reported_a_partial_last_line_is_not(tmp_path):
    good = json.dumps({"episode": 1, "outcome": "success"})
    (tmp_path / "history.jsonl").write_text(good + "\n{\"episode\": 2, \"outc")
    assert len(ex.read_history(tmp_path)) == 1
    (tmp_path / "history.jsonl").write_text(good + "\nnot json\n" + json.dumps({"episode": 2, "outcome": "success"}))
    with pytest.raises(ex.ExperimentError, match=r"history.jsonl:2"):
        ex.read_history(tmp_path)
    (tmp_path / "history.jsonl").write_text(good + "\n" + json.dumps({"episode": 3, "outcome": "success"}))
    with pytest.raises(ex.ExperimentError, match="episode 3 follows 1"):
        ex.read_history(tmp_path)
    with pytest.raises(ex.ExperimentError, match="no history.jsonl"):
        ex.read_history(tmp_path / "nope")


def test_overtake_without_a_source_run_says_what_to_do(tmp_path):
    cfg = ex.load_experiment_config(overrides={"runs_dir": str(tmp_path)})
    with pytest.raises(ex.ExperimentError, match="train --only bimab"):
        ex.overtake(cfg)


# --- aggregation maths --------------------------------------------------------------------


def _csv(path, success):
    cells = [CellResult(0, 0, {"success": s, "collision": 10 - s}, []) for s in [success]]
    cells.append(CellResult(1, 3, {"timeout": 10}, []))
    write_outputs(cells, path)
    return ex.read_eval_csv(path.with_suffix(".csv"))


def test_mean_and_std_across_seeds(tmp_path):
    tables = [_csv(tmp_path / f"s{k}", s) for k, s in enumerate((6, 8, 10))]
    agg = ex.aggregate_cells(tables)
    a = agg[(0, 0)]
    assert a["n"] == 3
    np.testing.assert_allclose(a["mean"], [80.0, 20.0, 0.0])
    np.testing.assert_allclose(a["std"], [20.0, 20.0, 0.0])     # sample std of 60, 80, 100
    np.testing.assert_allclose(agg[(1, 3)]["mean"], [0.0, 0.0, 100.0])
    one = ex.aggregate_cells(tables[:1])[(0, 0)]
    assert np.all(np.isnan(one["std"]))
    cfg = ex.load_experiment_config(overrides={"evaluation": {"n_sv": [0, 3], "tasks": ["left", "straight"]}})
    md = ex.table_markdown([("M", agg, 3)], cfg)
    assert "| M | left | 80±20 / 20±20 / 0±0 | – | 3 |" in md


def _history(outcomes):
    return [{"episode": k + 1, "outcome": "success" if o else "collision", "n_sv": 0} for k, o in enumerate(outcomes)]


def test_sample_efficiency_on_a_synthetic_history():
    # 100 failures then successes: the 10-episode rolling rate reaches 0.9 (9 of 10) at episode 109
    recs = _history([0] * 100 + [1] * 50)
    ep, final = ex.episodes_to_fraction(recs, window=10, fraction=0.9)
    assert final == 1.0 and ep == 109
    # final success 0.5 (alternating tail): 90% of it = 0.45 is reached by the first full window after 100
    recs = _history([0] * 100 + [1, 0] * 50)
    ep, final = ex.episodes_to_fraction(recs, window=10, fraction=0.9)
    assert final == 0.5 and ep == 109
    assert ex.episodes_to_fraction(_history([0] * 30), 10, 0.9) == (None, 0.0)
    ep, final = ex.episodes_to_fraction(_history([1] * 5), 10, 0.9)
    assert ep is None and np.isnan(final)


def test_mean_std_curve_on_the_common_range():
    a, b = _history([1] * 40), _history([0] * 30)
    x, mean, std = ex.mean_std_curve([a, b], window=10)
    assert x[0] == 10 and x[-1] == 30
    np.testing.assert_allclose(mean, 0.5)
    np.testing.assert_allclose(std, np.std([1.0, 0.0], ddof=1))
    x, mean, std = ex.mean_std_curve([a], window=10)
    assert std is None and x[-1] == 40


def test_mean_counts_for_table1():
    logs = [{"count_0": 2.0, "count_0_1": 2.0, "cluster_prob_0": 1.0}, {"count_0": 4.0, "count_0_1": 1.0}]
    assert ex.mean_counts(logs) == {"count_0": 3.0, "count_0_1": 1.5}
    assert "| 0 | 3.0 | 0.0 | 1.5 | 0.0 |" in ex.counts_markdown(ex.mean_counts(logs))


# --- n_slow: the env option and the overtaking wrapper ------------------------------------


@pytest.fixture(scope="module")
def lane_env():
    from bimacppo_learning.env import IntersectionEnv

    return IntersectionEnv(map_id="three_lane_straight")


def _n_slow(env):
    return sum(sv.slow for sv in env.unwrapped.world.svs)


def test_env_n_slow_option(lane_env):
    lane_env.reset(options={"n_sv": 3, "task": "straight", "scenario_seed": 5, "n_slow": 2})
    assert _n_slow(lane_env) == 2
    lane_env.reset(options={"n_sv": 3, "task": "straight", "scenario_seed": 5})
    assert _n_slow(lane_env) == 0                      # absent: the Scenario default, no slow SV
    for bad in (4, -1, True, 1.5):
        with pytest.raises(ValueError, match="n_slow"):
            lane_env.scenario_from_options({"n_sv": 3, "task": "straight", "n_slow": bad})
    sc = lane_env.scenario_from_options({"n_sv": 3, "task": "straight", "n_slow": None})
    assert sc.n_slow is None


def test_slow_traffic_wrapper_folds_the_task_and_draws_n_slow(lane_env):
    env = ex.SlowTraffic(lane_env, n_slow_max=2)
    seen = set()
    for seed in range(30):
        _, info = env.reset(seed=seed, options={"n_sv": 3, "task": 0})
        assert lane_env.scenario.task == "straight"
        k = _n_slow(env)
        assert 0 <= k <= 2 and k == lane_env.scenario.n_slow
        seen.add(k)
    assert seen == {0, 1, 2}
    env.reset(seed=3, options={"n_sv": 1, "task": 2})
    assert _n_slow(env) <= 1
    assert all(ex.draw_n_slow(s, 3, 2) == ex.draw_n_slow(s, 3, 2) for s in range(10))
    assert {ex.draw_n_slow(s, 3, 2) for s in range(200)} == {0, 1, 2}
    assert {ex.draw_n_slow(s, 1, 2) for s in range(200)} == {0, 1}
