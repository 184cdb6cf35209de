"""scripts/constant_actions.py: one row per waypoint, one cell per speed, counts that add up to
the episodes, and constant actions that really differ in outcome (the far waypoint at full speed
and WP0 at 0 m/s cannot both end like the middle of the table)."""
import re

from conftest import load_script


def test_constant_action_table_counts_every_episode_of_every_action(capsys):
    mod = load_script("constant_actions")
    assert mod.main(["--task", "right", "--n-sv", "0", "--episodes", "2"]) == 0
    rows = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| WP")]
    assert [r.split("|")[1].strip() for r in rows] == [f"WP{k}" for k in range(5)]
    cells = [[tuple(int(x) for x in re.findall(r"\d+", c)) for c in r.split("|")[2:-1]] for r in rows]
    assert all(len(r) == 5 and all(len(c) == 3 and sum(c) == 2 for c in r) for r in cells)
    assert len({c for r in cells for c in r}) > 1          # the actions lead to different outcomes
    assert cells[0][0] == (0, 0, 2)                         # WP0 at 0 m/s (the paper's stop): stands
