"""scripts/bench_train.py: copies run at once, and their aggregate throughput is reported."""
import subprocess
import sys

import pytest

from conftest import REPO


def test_concurrent_copies_report_one_copy_and_the_aggregate():
    out = subprocess.run([sys.executable, str(REPO / "scripts/bench_train.py"), "--episodes", "20", "--only", "batched",
                          "--concurrent", "2", "--omp-wait", "passive"], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "2 copies at once, OMP_WAIT_POLICY passive" in out.stdout
    row = next(line for line in out.stdout.splitlines() if line.startswith("| batched |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    one, together = float(cells[2]), float(cells[3])
    # the row's copy is the median (of two: the slower), the aggregate the sum over both; both
    # printed to 0.1 episodes/s, so 2 * one may overstate the exact sum by up to 0.1 and the
    # printed sum understate it by 0.05 (3.96 + 3.98 prints as one 4.0, together 7.9)
    assert one > 0.0 and together >= 2.0 * one - 0.15
    bad = subprocess.run([sys.executable, str(REPO / "scripts/bench_train.py"), "--concurrent", "0"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--concurrent must be in 1..64" in bad.stderr


def test_a_bounded_spin_and_the_nmpc_threads_reach_the_children_settings(monkeypatch):
    from conftest import load_script

    monkeypatch.delenv("GOMP_SPINCOUNT", raising=False)
    mod = load_script("bench_train")
    env = mod.child_env(omp_spin=50000)
    assert env["OMP_WAIT_POLICY"] == "ACTIVE" and env["GOMP_SPINCOUNT"] == "50000" and env["TQDM_DISABLE"] == "1"
    passive = mod.child_env(omp_wait="passive")
    assert passive["OMP_WAIT_POLICY"] == "PASSIVE" and "GOMP_SPINCOUNT" not in passive
    # the thread count joins a row's own NMPC overrides without changing the table of rows
    uncut = mod.mpc_overrides("batched-uncut", 1)
    assert uncut["fast"]["threads"] == 1 and uncut["fast"]["second_start_cut"] is None
    assert "threads" not in mod.MPC["batched-uncut"]["fast"]
    assert mod.mpc_overrides("batched", None) == {} and mod.mpc_overrides("batched", 0) == {"fast": {"threads": 0}}


def test_bad_spin_and_thread_options_are_one_usage_error():
    for argv, text in ((["--omp-spin", "-1"], "--omp-spin must be >= 0"),
                       (["--omp-spin", "10", "--omp-wait", "passive"], "cannot go with --omp-wait passive"),
                       (["--mpc-threads", "-2"], "--mpc-threads must be >= 0")):
        bad = subprocess.run([sys.executable, str(REPO / "scripts/bench_train.py"), *argv],
                             capture_output=True, text=True, timeout=60)
        assert bad.returncode == 2 and text in bad.stderr, (argv, bad.stderr)


FAKE_CLI = '''
import json, pathlib, subprocess, sys


def train_main(argv):
    """A stand-in trainer: records the arguments it got, writes one history line per episode."""
    a = dict(zip(argv[::2], argv[1::2]))
    run = pathlib.Path(a["--run-dir"])
    run.mkdir(parents=True)
    assert "--no-progress" in argv and pathlib.Path(a["--env-config"]).read_text() == "who: the commit's own\\n"
    n = int(a["--episodes"])
    with open(run / "history.jsonl", "w") as f:
        for e in range(n):
            f.write(json.dumps({"episode": e + 1, "env_steps": 7 * (e + 1), "outcome": "success" if e % 2 else "timeout"}) + "\\n")
    print(json.dumps({"module": __file__}), file=sys.stderr)
    # a worker process's CPU time counts towards the run's (it is reaped before the run ends)
    subprocess.run([sys.executable, "-c", BURN], check=True)
    return 0


BURN = "import time\\nt = time.process_time()\\nwhile time.process_time() - t < 0.3:\\n    pass"
'''


def _repo_with_trainer(tmp_path, cli=FAKE_CLI, setup_line="'bimacppo-train = oldpkg.cli:train_main'"):
    """A git repository with one commit whose package declares a bimacppo-train console script."""
    repo = tmp_path / "repo"
    (repo / "oldpkg" / "oldpkg" / "config").mkdir(parents=True)
    (repo / "oldpkg" / "oldpkg" / "__init__.py").write_text("")
    (repo / "oldpkg" / "oldpkg" / "cli.py").write_text(cli)
    (repo / "oldpkg" / "oldpkg" / "config" / "env_extended.yaml").write_text("who: the commit's own\n")
    (repo / "oldpkg" / "setup.py").write_text(f"entry_points = {{'console_scripts': [{setup_line}]}}\n")
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "old trainer"], check=True)
    (repo / "oldpkg" / "oldpkg" / "cli.py").write_text("raise SystemExit('the working tree, not the commit')\n")
    return repo


def test_a_ref_row_runs_the_commits_own_trainer_from_its_exported_tree(tmp_path):
    from conftest import load_script

    mod = load_script("bench_train")
    repo = _repo_with_trainer(tmp_path)
    # the working tree's edit after the commit is not what runs; the commit's CLI and config are
    res = mod.run_ref("HEAD", 6, 3, "/elsewhere/env_extended.yaml", copies=2, root=repo)
    assert len(res) == 2
    for r in res:
        assert r["episodes"] == 6 and r["decisions"] == 42 and r["ticks"] is None and r["timing"] is None
        assert r["success"] == 0.5 and r["wall"] > 0.0
        assert r["cpu"] >= 0.3
    head = subprocess.run(["git", "-C", str(repo), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True, check=True).stdout.strip()
    assert all(r["commit"] == head for r in res)
    r = {**res[0], "aggregate": 2.0, "eps_all": [1.0]}
    row = mod.table_row("ref", "HEAD", r, r, cores=2)
    cells = [c.strip() for c in row.strip().strip("|").split("|")]
    # a symbolic ref is shown with the commit it resolved to; a hash is shown once
    assert cells[0] == f"bimacppo-train at HEAD = {head}" and cells[4] == "-" and cells[6] == "1.00x"
    assert float(cells[7]) == pytest.approx(1e3 * r["cpu"] / 6, abs=0.06)
    assert float(cells[8]) == pytest.approx(2 * 6 / r["cpu"], abs=0.06)
    # a ref row's trainer times no parts, so it has no CPU split
    assert cells[9] == "-" and len(cells) == 18 and cells[-1] == "50%"
    assert mod.table_row("ref", head[:5], r, r).startswith(f"| bimacppo-train at {head[:5]} |")


def test_a_ref_that_cannot_run_is_named(tmp_path):
    from conftest import load_script

    mod = load_script("bench_train")
    repo = _repo_with_trainer(tmp_path, setup_line="'bimacppo-evaluate = oldpkg.cli:train_main'")
    with pytest.raises(mod.RefError, match="--ref no-such-ref: not a commit"):
        mod.export_ref("no-such-ref", tmp_path / "x", repo)
    tree = tmp_path / "tree"
    mod.export_ref("HEAD", tree, repo)
    with pytest.raises(mod.RefError, match="no package declares the bimacppo-train console script"):
        mod.ref_layout(tree, "env_extended.yaml")
    (tree / "oldpkg" / "setup.py").write_text("x = ['bimacppo-train = oldpkg.cli:train_main']\n")
    with pytest.raises(mod.RefError, match="has no config/env_other.yaml"):
        mod.ref_layout(tree, "a/b/env_other.yaml")
    paths, entry, cfg = mod.ref_layout(tree, "a/b/env_extended.yaml")
    assert paths == [str(tree / "oldpkg")] and entry == "oldpkg.cli:train_main"
    assert cfg == str(tree / "oldpkg" / "oldpkg" / "config" / "env_extended.yaml")
    bad = subprocess.run([sys.executable, str(REPO / "scripts/bench_train.py"), "--ref", "no-such-ref-xyz"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--ref no-such-ref-xyz: not a commit" in bad.stderr, bad.stderr


def test_the_closing_line_prices_the_target_in_cpu_per_episode():
    from conftest import load_script

    mod = load_script("bench_train")
    base = {"episodes": 100, "wall": 10.0, "cpu": 15.0}     # 10 episodes/s
    last = {"episodes": 100, "wall": 4.0, "cpu": 6.0}       # 60 ms of CPU per episode
    line = mod.target_line(base, last, 10.0, 2)
    # 10x is 100 episodes/s; two cores then give each episode 20 ms; 60 ms is 3x that, and two
    # cores busy with 60 ms episodes finish 33.3 per second, 3.33x the first row
    assert line.startswith("10x the first row is 100.0 episodes/s: on 2 cores at most 20.0 ms of CPU per episode")
    assert "the last row spends 60.0 ms (3.00x that)" in line and line.endswith("33.3 episodes/s, 3.33x the first row")
    assert "NMPC and PPO update" not in line         # a row without a timed split (a --ref row) names no parts
    # an in-process row's parts: the NMPC out of env stepping, the rest of the run's CPU as other
    timing = {"env_cpu": 3.0, "mpc_cpu_seconds": 2.0, "policy_cpu": 0.5, "update_cpu": 1.5, "total_cpu": 5.5}
    split = mod.cpu_split({**last, "timing": timing, "workers": 1})
    assert split == pytest.approx({"nmpc": 0.02, "env": 0.01, "policy": 0.005, "update": 0.015, "other": 0.01})
    line = mod.target_line(base, {**last, "timing": timing, "workers": 1}, 10.0, 2)
    assert line.endswith("its NMPC and PPO update alone spend 35.0 ms (1.75x the budget)")
    # where envs step in worker processes, the process's own parts miss their CPU: no split
    assert mod.cpu_split({**last, "timing": timing, "workers": 2}) is None
    bad = subprocess.run([sys.executable, str(REPO / "scripts/bench_train.py"), "--target-ratio", "0"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--target-ratio must be > 0" in bad.stderr
