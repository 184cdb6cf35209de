"""bimacppo-experiments statistics and tables on synthetic data: history parsing, mean and
spread over seeds, sample efficiency, curves, Table I counts."""
import json

import numpy as np
import pytest

from bimacppo_learning import experiments as ex
from bimacppo_learning.evaluate import CellResult, write_outputs


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




def test_success_matrix_needs_every_cell_of_every_run():
    from bimacppo_learning.experiments.stats import success_matrix

    t1 = {(0, 0): (100.0, 0.0, 0.0), (0, 3): (90.0, 10.0, 0.0)}
    t2 = {(0, 0): (80.0, 20.0, 0.0), (0, 3): (70.0, 30.0, 0.0)}
    assert success_matrix([t1, t2], [(0, 0), (0, 3)]).tolist() == [[100.0, 90.0], [80.0, 70.0]]
    with pytest.raises(ValueError, match="every run needs every cell"):
        success_matrix([t1, {(0, 0): (1.0, 0.0, 0.0)}], [(0, 0), (0, 3)])


def test_iqm_drops_the_outer_quartiles_and_intervals_cover_it():
    from bimacppo_learning.experiments.stats import iqm_intervals

    x = np.array([[0.0], [50.0], [60.0], [100.0]])   # IQM of 4 scores: the middle two
    e = iqm_intervals({"x": x, "one": np.array([[40.0, 60.0]])}, reps=300)
    assert e["x"]["iqm"] == pytest.approx(55.0) and e["x"]["mean"] == pytest.approx(52.5)
    lo, hi = e["x"]["iqm_ci"]
    assert lo <= 55.0 <= hi and hi - lo > 0.0
    assert e["one"]["runs"] == 1 and e["one"]["iqm_ci"] == (e["one"]["iqm"], e["one"]["iqm"])   # nothing to resample
    again = iqm_intervals({"x": x, "one": np.array([[40.0, 60.0]])}, reps=300)
    assert again == e                                                                        # seeded


def test_probability_of_improvement_orders_methods():
    from bimacppo_learning.experiments.stats import improvement_probability

    rng = np.random.default_rng(1)
    good, bad = rng.uniform(90, 100, (10, 6)), rng.uniform(20, 40, (3, 6))
    assert improvement_probability(good, bad, reps=300)["p"] == 1.0
    assert improvement_probability(bad, good, reps=300)["p"] == 0.0
    same = improvement_probability(good, good, reps=300)
    assert same["p"] == 0.5 and same["ci"][0] < 0.5 < same["ci"][1]
    with pytest.raises(ValueError, match="same cells"):
        improvement_probability(good, bad[:, :3])
