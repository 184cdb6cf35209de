"""The benchmark script runs end to end on a tiny sample and writes its markdown table."""
import numpy as np

from bimacppo_mpc import MPCConfig
import pytest

from bimacppo_mpc.bench import BenchConfig, generate_problems, main, make_route, throughput_row


def test_routes_are_continuous_and_end_with_the_turned_heading():
    bc = BenchConfig.load()
    for kind, end_heading in [("straight", 0.0), ("left", np.pi / 2), ("right", -np.pi / 2)]:
        r = make_route(kind, 10.0, bc)
        steps = np.hypot(*np.diff(r[:, :2], axis=0).T)
        assert steps.max() < 1.5 * bc.waypoint_spacing
        assert r[-1, 2] == np.float64(end_heading)


def test_generated_problems_are_closed_loop_and_within_bounds():
    cfg, bc = MPCConfig.load(), BenchConfig.load()
    eps = generate_problems(cfg, bc, episodes=2)
    assert len(eps) == 2
    for ep in eps:
        assert ep.X0.shape == (bc.steps, 4) and ep.Xref.shape == (bc.steps, 4) and ep.Uprev.shape == (bc.steps, 2)
        assert np.all(np.isfinite(ep.X0))
        assert np.all((ep.X0[:, 2] >= cfg.v_min - 1e-9) & (ep.X0[:, 2] <= cfg.v_max + 1e-9))
        assert set(np.unique(ep.Xref[:, 2])) <= set(bc.ref_speeds)
        # successive states follow from the recorded inputs (u_prev of step k+1 = u applied at k)
        dx = np.hypot(*np.diff(ep.X0[:, :2], axis=0).T)
        assert np.all(dx <= cfg.dt * cfg.v_max + 1e-9)


def test_main_writes_a_markdown_table(tmp_path, capsys):
    out = tmp_path / "r.md"
    assert main(["--episodes", "1", "--repeats", "2", "--out", str(out)]) == 0
    text = out.read_text()
    assert text.startswith("| metric | fast | ipopt |")
    assert "median solve time" in text and "cost gap" in text and "throughput B=64" in text
    assert "(median of 2)" in text
    assert "median solve time" in capsys.readouterr().out


def test_throughput_row_gives_the_median_of_the_pairs_and_their_range():
    # one run pair lucky on 2 threads, one unlucky: the ratio is that of each pair, not of the medians
    thr = {(8, 1): [100.0, 200.0, 150.0], (8, 2): [190.0, 300.0, 150.0]}
    label, cells, _, ratio = throughput_row(8, (1, 2), thr, 3)
    assert label == "solve_batch throughput B=8, 1 / 2 thread(s) [problems/s]"
    assert cells == "150 / 190 (median of 3)"
    assert ratio == "1.50x (1.00-1.90)"
    assert throughput_row(8, (1,), {(8, 1): [5.0]}, 1)[1:] == ("5", "", "")


def test_repeats_below_one_are_refused(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--episodes", "1", "--repeats", "0"])
    assert e.value.code == 2 and "--repeats must be >= 1" in capsys.readouterr().err
