"""Ride comfort figures: hand-worked command sequences, and their place in the evaluation."""
import csv
import io
import math

import numpy as np
import pytest

from bimacppo_learning.comfort import LOCK_TOLERANCE, Comfort
from bimacppo_learning.evaluate import evaluate, to_csv, to_markdown


def test_lock_share_reversals_and_jerk_by_hand():
    c = Comfort(delta_max=0.6, dt=0.1)
    # ticks: left lock, right lock (a reversal), right lock, free, left lock (no reversal: a free tick between)
    c.add_episode([[0.0, 0.6], [1.0, -0.6], [1.0, -0.6 + LOCK_TOLERANCE / 2], [0.0, 0.1], [0.0, 0.6]])
    assert (c.ticks, c.lock_ticks, c.pairs, c.reversals) == (5, 4, 4, 1)
    assert c.full_lock_pct == pytest.approx(80.0) and c.reversal_pct == pytest.approx(25.0)
    # jerk: (1-0)/0.1, 0, (0-1)/0.1, 0 -> RMS sqrt((100 + 100) / 4)
    assert c.rms_jerk == pytest.approx(math.sqrt(50.0))
    # a second episode: no pair spans the episode boundary
    c.add_episode([[3.0, -0.6]])
    assert (c.ticks, c.pairs, c.reversals) == (6, 4, 1) and c.rms_jerk == pytest.approx(math.sqrt(50.0))
    empty = Comfort(delta_max=0.6, dt=0.1)
    empty.add_episode(np.zeros((0, 2)))
    assert math.isnan(empty.full_lock_pct) and math.isnan(empty.rms_jerk)


def test_go_stop_alternations_by_hand():
    c = Comfort(delta_max=0.6, dt=0.1)
    # decisions: go, [stop], go, go, stop, stop, [go], stop: the bracketed ones sit between two
    # decisions of the other kind; the held stop (two in a row) does not count
    c.add_episode(np.zeros((3, 2)), [8.0, 0.0, 4.0, 4.0, 0.0, 0.0, 2.0, 0.0])
    assert (c.triples, c.alternations) == (6, 2) and c.alternation_pct == pytest.approx(200 / 6)
    c.add_episode(np.zeros((3, 2)), [0.0, 2.0])               # two decisions: no triple
    assert (c.triples, c.alternations) == (6, 2)
    c.add_episode(np.zeros((3, 2)), [0.0, 2.0, 0.0, 2.0])     # stop-go-stop-go: both middle ones alternate
    assert (c.triples, c.alternations) == (8, 4)
    assert math.isnan(Comfort(delta_max=0.6, dt=0.1).alternation_pct)


def test_every_evaluation_reports_comfort_per_cell():
    res = evaluate(None, "dual_lane_4way", [1], [0], episodes=2, workers=1, random_row=False)
    (cell,) = res
    q = cell.comfort
    assert q is not None and q.ticks > 20 and q.pairs == q.ticks - 2      # 2 episodes, pairs within each
    assert 0.0 <= q.full_lock_pct <= 100.0 and 0.0 <= q.reversal_pct <= 100.0 and q.rms_jerk >= 0.0
    row = next(csv.DictReader(io.StringIO(to_csv(res))))
    assert float(row["full_lock_pct"]) == pytest.approx(q.full_lock_pct, abs=0.01)
    assert float(row["rms_jerk"]) == pytest.approx(q.rms_jerk, abs=0.001)
    md = to_markdown(res)
    assert "Ride comfort" in md and f"{q.full_lock_pct:.1f} / {q.reversal_pct:.1f} / {q.rms_jerk:.1f}" in md
    assert q.triples > 0 and float(row["go_stop_alternation_pct"]) == pytest.approx(q.alternation_pct, abs=0.01)
