"""scripts/seed_targets.py: per-run validation / test cells, whether each run meets the targets
(>= threshold in every N_sv = 3 cell, 100 % on the empty road), counts per set; bad input is one
error line."""
from conftest import load_script
from bimacppo_learning.evaluate import CellResult, write_outputs


def _run(tmp_path, name, val, test):
    """A run directory with val_policy.csv / test_policy.csv from {(task index, n_sv): successes of 100}."""
    from collections import Counter
    run = tmp_path / name
    run.mkdir()
    for stem, cells in (("val_policy", val), ("test_policy", test)):
        if cells is not None:
            res = [CellResult(j, n, Counter(success=s, collision=100 - s), []) for (j, n), s in cells.items()]
            write_outputs(res, str(run / stem), stem)
    return run


def _cells(busy, empty=(100, 100, 100)):
    return {**{(j, 3): s for j, s in enumerate(busy)}, **{(j, 0): s for j, s in enumerate(empty)}}


def test_runs_meet_the_targets_only_with_every_cell(tmp_path, capsys):
    mod = load_script("seed_targets")
    a = _run(tmp_path, "s0", _cells((99, 96, 95)), _cells((98, 95, 97)))
    b = _run(tmp_path, "s1", _cells((99, 96, 95)), _cells((98, 94, 97)))            # one test cell at 94
    c = _run(tmp_path, "s2", _cells((99, 99, 99), (100, 99, 100)), _cells((99, 99, 99)))  # empty road 99 on validation
    d = _run(tmp_path, "s3", _cells((97, 97, 97)), None)                           # no test CSV
    assert mod.main([str(a), str(b), str(c), str(d), "--label", "A"]) == 0
    out = capsys.readouterr().out
    assert "| s0 | A | 99 / 96 / 95 | 100 / 100 / 100 | 98 / 95 / 97 | 100 / 100 / 100 | yes | yes |" in out
    assert "| s1 | A | 99 / 96 / 95 | 100 / 100 / 100 | 98 / 94 / 97 | 100 / 100 / 100 | yes | no |" in out
    assert "| s2 | A | 99 / 99 / 99 | 100 / 99 / 100 | 99 / 99 / 99 | 100 / 100 / 100 | no | yes |" in out
    assert "| s3 | A | 97 / 97 / 97 | 100 / 100 / 100 | - | - | yes | no |" in out
    assert "| A | 4 | 3 of 4 | 2 of 4 |" in out
    assert mod.main([str(a), str(b), "--versus", str(c), "--label", "A", "B", "--threshold", "96"]) == 0
    out = capsys.readouterr().out
    assert "| A | 2 | 0 of 2 | 0 of 2 |" in out and "| B | 1 | 0 of 1 | 1 of 1 |" in out


def test_bad_input_is_one_error_line(tmp_path, capsys):
    mod = load_script("seed_targets")
    assert mod.main([str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("seed_targets.py: error: not a run directory")
    run = tmp_path / "bad"
    run.mkdir()
    (run / "val_policy.csv").write_text("task,n_sv,success_pct\nleft,3,abc\n")
    assert mod.main([str(run)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "val_policy.csv:2: malformed evaluation row" in err[0]
    assert mod.main([str(run), "--threshold", "101"]) == 2
    assert "--threshold must be in 0..100" in capsys.readouterr().err
