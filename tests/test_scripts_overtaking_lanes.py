"""scripts/overtaking_lanes.py: the lane distance the overtaking scenarios ask for."""
from conftest import load_script


def test_without_slow_svs_every_lane_is_free_and_two_slow_svs_sometimes_block_two_lanes(capsys):
    script = load_script("overtaking_lanes")
    none = script.distances("validation", 30, slow_max=0)
    assert none == {0: 30}
    two = script.distances("validation", 100, slow_max=2)
    assert sum(two.values()) == 100 and set(two) <= {0, 1, 2} and two[2] > 0 and two[1] > 0
    assert script.main(["--seed-set", "validation", "--episodes", "100"]) == 0
    out = capsys.readouterr().out
    assert f"  2: {two[2]} scenarios" in out


def test_bad_arguments_end_in_a_usage_error(capsys):
    script = load_script("overtaking_lanes")
    for argv in (["--episodes", "0"], ["--slow-svs", "4"]):
        try:
            script.main(argv)
        except SystemExit as exc:
            assert exc.code == 2
        else:
            raise AssertionError(f"{argv} accepted")
        assert "error:" in capsys.readouterr().err
