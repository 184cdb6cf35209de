"""bimacppo-experiments config: errors name the file and the key, paths reach bimacppo-train,
the packaged grid is the paper's, and a run directory's recorded settings decide whether it
counts as this config's run."""
import dataclasses
import json
import pathlib

import pytest

from bimacppo_learning import experiments as ex

STUDIES = pathlib.Path(__file__).resolve().parent.parent / "studies" / "config"
ENV_EXTENDED = "bimacppo_learning/bimacppo_learning/config/env_extended.yaml"


def test_unknown_method_is_an_error(tmp_path, capsys):
    cfg = ex.load_experiment_config(overrides={"runs_dir": str(tmp_path)})
    with pytest.raises(ex.ExperimentError, match="unknown method.*'ppo'"):
        ex.train(cfg, only=["ppo"])
    p = tmp_path / "exp.yaml"
    p.write_text(f"runs_dir: {tmp_path}\n")
    assert ex.main(["--config", str(p), "train", "--only", "ppo"]) == 2
    assert "unknown method" in capsys.readouterr().err


@pytest.mark.parametrize("doc, key", [
    ("bogus: 1\n", "bogus"),
    ("episodes: many\n", "episodes"),
    ("episodes: 0\n", "episodes"),
    ("methods: [bimab, ppo]\n", "methods"),
    ("seeds: [0, 1, 0]\n", "seeds"),
    ("seeds: []\n", "seeds"),
    ("evaluation: {episodes: 5000}\n", "evaluation.episodes"),
    ("evaluation: {tasks: [left, uturn]}\n", "evaluation.tasks"),
    ("evaluation: {n_sv: [0, 4]}\n", "evaluation.n_sv"),
    ("overtake: {speed: 3}\n", "overtake.speed"),
    ("report: {efficiency_fraction: 1.5}\n", "report.efficiency_fraction"),
    ("zero_shot_map: three_lane_straight\n", "zero_shot_map"),
    ("runs_dir: ''\n", "runs_dir"),
    ("train: 2\n", "train"),
])
def test_config_errors_name_file_and_key(tmp_path, doc, key):
    p = tmp_path / "bad.yaml"
    p.write_text(doc)
    with pytest.raises(ex.ConfigError) as ei:
        ex.load_experiment_config(p)
    assert str(ei.value).startswith(f"{p}: ") and f"'{key}'" in str(ei.value)


def test_a_config_error_is_one_line_and_exit_2(tmp_path, capsys):
    p = tmp_path / "bad.yaml"
    p.write_text("train: {num_env: 4}\n")
    assert ex.main(["--config", str(p), "report"]) == 2
    err = capsys.readouterr().err
    assert err == f"bimacppo-experiments: error: {p}: unknown key 'train.num_env' (did you mean 'num_envs'?)\n"


def test_an_unknown_overlay_key_is_refused_with_a_suggestion(tmp_path):
    p = tmp_path / "typo.yaml"
    p.write_text("episodes: 10\nevaluation: {episode: 10}\n")
    with pytest.raises(ex.ConfigError, match=r"typo.yaml: unknown key 'evaluation.episode' "
                                             r"\(did you mean 'episodes'\?\)"):
        ex.load_experiment_config(p)
    with pytest.raises(ex.ConfigError, match=r"overrides: unknown key 'seed' \(did you mean 'seeds'\?\)"):
        ex.load_experiment_config(overrides={"seed": [0]})


def test_an_overlay_listing_one_key_keeps_every_other_packaged_default(tmp_path):
    packaged = ex.load_experiment_config()
    assert packaged == ex.ExperimentConfig()
    p = tmp_path / "one.yaml"
    p.write_text("evaluation: {workers: 1}\n")
    cfg = ex.load_experiment_config(p)
    assert cfg.evaluation == dataclasses.replace(packaged.evaluation, workers=1) and packaged.evaluation.workers != 1
    assert dataclasses.replace(cfg, evaluation=packaged.evaluation, source=packaged.source) == packaged
    assert cfg.source == f"{p} over {packaged.source}"
    dotted = ex.load_experiment_config(overrides={"overtake.episodes": 7})
    assert dotted.overtake == dataclasses.replace(packaged.overtake, episodes=7) and dotted.train == packaged.train


def test_the_studies_overlay_changes_only_what_it_lists(monkeypatch):
    monkeypatch.chdir(STUDIES.parent.parent)             # its paths are the repository root's
    packaged = ex.load_experiment_config()
    ext = ex.load_experiment_config(STUDIES / "experiments_ext2k.yaml")
    assert (ext.episodes, ext.runs_dir) == (2000, "runs/exp-ext2k")
    assert ext.train == dataclasses.replace(packaged.train, env_config=ENV_EXTENDED, num_envs=2, vector="async",
                                            ppo_config="studies/config/ppo_per_env.yaml")
    assert dataclasses.replace(ext, episodes=packaged.episodes, runs_dir=packaged.runs_dir, train=packaged.train,
                               source=packaged.source) == packaged


def test_replace_is_checked_like_a_file():
    cfg = ex.load_experiment_config()
    with pytest.raises(ex.ConfigError, match=r"key 'methods' item 1 must be one of"):
        dataclasses.replace(cfg, methods=("bimab", "ppo"))
    with pytest.raises(ex.ConfigError, match=r"key 'reference_drivers' must not repeat"):
        dataclasses.replace(cfg.evaluation, reference_drivers=("go", "go"))
    assert dataclasses.replace(cfg.evaluation, reference_drivers=()).reference_drivers == ()


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
    with pytest.raises(ex.ConfigError, match=rf"{bad}: key 'train.env_config' no such file .*nope.yaml"):
        ex.load_experiment_config(bad)


def test_config_paths_are_relative_to_the_working_directory(tmp_path, monkeypatch):
    """Not to the config file: the grid runs from the repository root, whose paths a file names."""
    (tmp_path / "conf").mkdir()
    (tmp_path / "conf" / "env.yaml").write_text("action: {decision_every: 3}\n")
    p = tmp_path / "conf" / "exp.yaml"
    p.write_text("train: {env_config: env.yaml}\n")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ex.ConfigError, match=r"train.env_config' no such file 'env.yaml'"):
        ex.load_experiment_config(p)
    p.write_text("train: {env_config: conf/env.yaml}\n")
    assert ex.load_experiment_config(p).resolved().train.env_config == str(tmp_path / "conf" / "env.yaml")


def test_packaged_config_is_the_papers_grid():
    cfg = ex.load_experiment_config()
    assert set(cfg.methods) == set(ex.CURRICULA) and len(cfg.seeds) >= 3
    assert cfg.evaluation.episodes == 100 and cfg.overtake.test_episodes == 100


def test_overtake_without_a_source_run_says_what_to_do(tmp_path):
    cfg = ex.load_experiment_config(overrides={"runs_dir": str(tmp_path)})
    with pytest.raises(ex.ExperimentError, match="train --only bimab"):
        ex.overtake(cfg)




@pytest.mark.parametrize("doc, key", [
    ("train: {num_cpus: 0}\n", "train.num_cpus"),
    ("evaluation: {num_cpus: 1.5}\n", "evaluation.num_cpus"),
])
def test_resource_keys_are_checked(tmp_path, doc, key):
    p = tmp_path / "bad.yaml"
    p.write_text(doc)
    with pytest.raises(ex.ConfigError, match=f"'{key}'"):
        ex.load_experiment_config(p)


def test_resolved_config_has_absolute_paths(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "env.yaml").write_text("action: {decision_every: 3}\n")
    cfg = ex.load_experiment_config(overrides={"runs_dir": "runs", "train": {"env_config": "env.yaml"}})
    r = cfg.resolved()
    assert r.runs_dir == str(tmp_path / "runs") and r.train.env_config == str(tmp_path / "env.yaml")
    assert r.run_dir("bimab", 0) == tmp_path / "runs" / "dual_lane_4way" / "bimab-s0"
    assert r.train.ppo_config is None and r.train.num_envs == cfg.train.num_envs


def test_a_run_counts_only_with_this_configs_settings(tmp_path):
    cfg = ex.load_experiment_config(overrides={"runs_dir": str(tmp_path), "episodes": 2})
    run = cfg.run_dir("bimab", 0)
    run.mkdir(parents=True)
    (run / "history.jsonl").write_text("".join(json.dumps({"episode": k, "outcome": "success"}) + "\n"
                                               for k in (1, 2)))
    (run / "policy.pt").write_bytes(b"")
    assert ex.run_status(cfg, "bimab", 0).done                 # nothing recorded: nothing to compare
    want = ex.run_settings(cfg, "bimab", 0)
    (run / "run.json").write_text(json.dumps({k: want[k] for k in ex.runs.RUN_JSON_KEYS}))
    assert ex.run_status(cfg, "bimab", 0).done
    (run / "run.json").write_text(json.dumps({**{k: want[k] for k in ex.runs.RUN_JSON_KEYS}, "map": "single_lane_4way"}))
    st = ex.run_status(cfg, "bimab", 0)
    assert not st.done and st.mismatch == ("map",) and st.state == "other settings"
    ex.runs.write_settings(run, {**want, "ppo": {**want["ppo"], "lr": 1.0}})   # experiment.json wins over run.json
    assert ex.run_status(cfg, "bimab", 0).mismatch == ("ppo",)
    ex.runs.write_settings(run, want)
    assert ex.run_status(cfg, "bimab", 0).done
    said = []
    assert ex.train(cfg, seeds=[0], only=["bimab"], echo=said.append) == 0 and "skipped" in said[0]
    ex.runs.write_settings(run, {**want, "seed": 7})
    said.clear()
    assert ex.train(cfg, seeds=[0], only=["bimab"], echo=said.append) == 1
    assert "FAILED" in said[0] and "other settings (seed" in said[0] and str(run / "train.log") in said[0]
