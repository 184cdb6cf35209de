"""BiMAB on a synthetic learner (the paper's §IV-B claims), and the plotting helpers."""
import numpy as np
import pytest

from bimacppo_curriculum import make_scheduler, plots
from bimacppo_curriculum.synthetic import SyntheticLearner, _window_shares, main, run, run_named

EPISODES = 5000
SEEDS = (0, 1, 2)


@pytest.fixture(scope="module")
def bimab_runs():
    return {s: run_named("bimab", s, EPISODES, log_every=50) for s in SEEDS}


# ------------------------------------------------------------------ the learner itself
def test_learner_skill_grows_with_practice_and_harder_scenarios_wait_for_easier_ones():
    a = SyntheticLearner(seed=0)
    c0 = a.competence.copy()
    for _ in range(50):
        a.practice(0, 2)
    assert a.competence[0, 2] > c0[0, 2] + 0.3          # practised scenario improved most
    assert a.competence[0, 2] > a.competence[0, 0] > c0[0, 0]   # same-cluster transfer, less
    # (3, left) from scratch vs after (2, left) was mastered: the prerequisite gates learning
    cold, warm = SyntheticLearner(seed=0), SyntheticLearner(seed=0)
    warm.competence[2, 0] = 0.95
    for _ in range(100):
        cold.practice(3, 0)
        warm.practice(3, 0)
    assert warm.competence[3, 0] > cold.competence[3, 0] + 0.2


def test_learner_returns_have_the_paper_shape():
    lr = SyntheticLearner(config={"return_noise": 0.0, "collision_share": 1.0}, seed=0)
    lr.competence[:] = 1.0
    succ = np.array([[lr.episode(i, j)[0] for j in range(3)] for i in range(4)])
    assert np.all(np.diff(succ, axis=0) > 0)            # more SVs: bigger success reward
    assert np.all(succ[1:, 2] < succ[1:, 0])             # right turn: fewest conflict points
    lr.competence[:] = 0.0
    fail = np.array([lr.episode(3, 0)[0] for _ in range(50)])
    assert np.all(fail < 0) and fail.min() < -3 * lr.config.collision_speed_min


# ------------------------------------------------------------------ §IV-B behaviour
def test_weight_moves_from_few_to_many_svs(bimab_runs):
    for seed, h in bimab_runs.items():
        first = _window_shares(h, 4, 0.0, 0.25)
        last = _window_shares(h, 4, 0.75, 1.0)
        assert last[3] > 0.5 and last[3] > first[3] + 0.2, (seed, first, last)
        assert last[0] < first[0], (seed, first, last)
        end = h[-1]
        w = [end[f"target_cluster_weight_{i}"] for i in range(4)]
        assert int(np.argmax(w)) == 3 and w[3] > w[0], (seed, w)
        # sampled times grow with N_sv overall (Table I's trend)
        counts = [end[f"count_{i}"] for i in range(4)]
        assert counts[3] == max(counts) and counts[0] == min(counts), (seed, counts)


def test_right_turn_arms_get_the_fewest_samples(bimab_runs):
    for seed, h in bimab_runs.items():
        end = h[-1]
        arms = np.array([[end[f"count_{i}_{j}"] for j in range(3)] for i in range(4)])
        tot = arms.sum(axis=0)
        assert tot[2] < tot[0] and tot[2] < tot[1], (seed, tot)
        assert arms[3, 2] < arms[3, 0] and arms[3, 2] < arms[3, 1], (seed, arms[3])
        # and the right-turn arm weight of the hardest cluster ends lowest
        w = [end[f"target_arm_weight_3_{j}"] for j in range(3)]
        assert int(np.argmin(w)) == 2, (seed, w)


def test_curriculum_beats_no_curriculum_on_the_synthetic_learner():
    fixed = run_named("fixed", 0, 2000, log_every=2000)[-1]["mean_competence"]
    bimab = run_named("bimab", 0, 2000, log_every=2000)[-1]["mean_competence"]
    assert bimab > fixed + 0.2


# ------------------------------------------------------------------ plots and table
def test_plots_and_table_from_a_history(tmp_path, bimab_runs):
    h = bimab_runs[0]
    for fn in (plots.plot_cluster_weights, plots.plot_arm_weights, plots.plot_cluster_probabilities):
        out = fn(h, tmp_path / f"{fn.__name__}.png")
        assert out.exists() and out.stat().st_size > 10_000
    table = plots.counts_table_markdown(h[-1])
    rows = [r for r in table.splitlines() if r.startswith("| ") and r[2].isdigit()]
    assert len(rows) == 4
    last = table.splitlines()[-1].split("|")
    assert int(last[2]) == EPISODES
    for i, r in enumerate(rows):
        cells = [int(c) for c in r.split("|")[2:6]]
        assert cells[0] == sum(cells[1:]) == int(h[-1][f"count_{i}"])


def test_plots_reject_histories_they_cannot_draw(tmp_path):
    with pytest.raises(ValueError, match="empty"):
        plots.plot_cluster_weights([], tmp_path / "x.png")
    s = make_scheduler("random", seed=0)
    hist = run(s, SyntheticLearner(seed=0), 20, log_every=10)
    with pytest.raises(ValueError, match="target_cluster_weight_0"):
        plots.plot_cluster_weights(hist, tmp_path / "x.png")
    assert plots.plot_cluster_probabilities(hist, tmp_path / "p.png").exists()


def test_cli_writes_the_figures(tmp_path, capsys):
    main(["--episodes", "300", "--seeds", "1", "--sync-interval", "50", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert "| N_sv | sampled |" in out and "| bimab |" in out and "| manual |" in out
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted(f"curriculum_synthetic_{k}.png" for k in ("fig5_clusters", "fig6_arms", "probs", "compare"))
