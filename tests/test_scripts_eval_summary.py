"""scripts/eval_summary.py: per-file rows, per-cell spread and rliable's aggregates over the
files, with the probability of improvement over a second set; bad files are one error line."""
import re

from conftest import load_script
from bimacppo_learning.evaluate import CellResult, write_outputs


def _csv(tmp_path, name, success):
    from collections import Counter
    res = [CellResult(j, n, Counter(success=s, collision=10 - s), []) for (j, n), s in success.items()]
    _, path = write_outputs(res, str(tmp_path / name), name)
    return str(path)


def test_summary_aggregates_runs_and_compares_with_a_baseline(tmp_path, capsys):
    mod = load_script("eval_summary")
    good = [_csv(tmp_path, f"s{k}", {(0, 0): 10, (0, 3): 9 - (k % 2), (2, 3): 8}) for k in range(4)]
    bad = [_csv(tmp_path, "rand", {(0, 0): 5, (0, 3): 3, (2, 3): 1})]
    assert mod.main([*good, "--versus", *bad, "--names", "learned", "random", "--n-sv", "3", "--reps", "200"]) == 0
    out = capsys.readouterr().out
    assert out.count("| " + str(tmp_path)) == 4
    assert "| N_sv = 0 left / straight / right | N_sv = 3 left / straight / right |" in out
    assert f"| {good[1]} | 86.7 | 100 / nan / nan | 80 / nan / 80 |" in out
    rows = {ln.split("|")[1].strip(): ln for ln in out.splitlines() if ln.startswith("| learned") or ln.startswith("| random")}
    assert re.search(r"\| learned \| 4 \| 8[0-9.]+ \[", rows["learned"])
    assert rows["random"].startswith("| random | 1 | 20.0 [20.0, 20.0]") and rows["random"].endswith("| 1.00 [1.00, 1.00] |")


def test_missing_cells_or_files_are_one_error_line(tmp_path, capsys):
    mod = load_script("eval_summary")
    a = _csv(tmp_path, "a", {(0, 0): 10, (0, 3): 9})
    b = _csv(tmp_path, "b", {(0, 0): 10})
    assert mod.main([a, b]) == 2
    assert "every run needs every cell" in capsys.readouterr().err
    assert mod.main([str(tmp_path / "nope.csv")]) == 2
