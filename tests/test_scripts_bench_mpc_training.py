"""scripts/bench_mpc_training.py: it records every problem the batched env hands the NMPC (per
slot, in order) and its replay with solve() sees the same problems the batch solved."""
import re

import numpy as np

from conftest import load_script


def _module():
    return load_script("bench_mpc_training")


def test_recording_keeps_every_batch_problem_per_slot_with_episode_starts():
    mod = _module()
    per_slot, batches, cfg = mod.record(3, 4, 0, str(mod.EXT), None)
    assert len(batches) >= 4 and all(b[0].shape == (3, 4) for b in batches)
    assert [len(s) for s in per_slot] == [len(batches)] * 3
    for t, (X0, Xr, Up, fresh) in enumerate(batches):
        for i in range(3):
            x0, xr, up, new = per_slot[i][t]
            assert np.array_equal(x0, X0[i]) and np.array_equal(xr, Xr[i]) and np.array_equal(up, Up[i])
            assert new == (i in fresh)
    assert batches[0][3] == [0, 1, 2]          # every slot starts an episode at the first batch
    t, it, st = mod.per_problem(cfg, per_slot)
    assert len(t) == 3 * len(batches) and (t > 0).all() and (it >= 1).all() and set(st) <= {1, 2}


def test_main_prints_every_figure(capsys):
    mod = _module()
    assert mod.main(["--decisions", "2", "--batch", "2", "--repeats", "1"]) == 0
    out = capsys.readouterr().out
    n = int(re.search(r"([\d,]+) problems", out).group(1).replace(",", ""))
    assert n >= 4
    for label in ("mean / median / p90 / p99 / max", "SQP iterations", "over 1 ms", "second start",
                  "new reference: share", "same reference: share", "1 / 2 threads", "ratio 2 threads",
                  "mostly new references / the rest", "peak RSS"):
        assert label in out, label


def test_a_problem_has_a_new_reference_at_an_episode_start_or_where_the_slots_reference_changed():
    mod = _module()
    a, b = np.array([1.0, 2.0, 3.0, 4.0]), np.array([1.0, 2.0, 3.0, 5.0])
    x, u = np.zeros(4), np.zeros(2)
    per_slot = [[(x, a, u, True), (x, a, u, False), (x, b, u, False), (x, b, u, True)],
                [(x, b, u, False), (x, b, u, False), (x, a, u, False), (x, a, u, False)]]
    assert mod.new_reference(per_slot).tolist() == [True, False, True, True, True, False, True, False]


def test_the_reference_split_puts_each_problems_time_on_its_side():
    mod = _module()
    t = np.array([4e-4, 1e-4, 1e-4, 2e-4])
    it = np.array([6, 2, 2, 4])
    st = np.array([2, 1, 1, 1])
    new = np.array([True, False, False, True])
    (n_name, n_val), (s_name, s_val) = mod.split_rows(t, it, st, new)
    assert n_name.startswith("new reference") and s_name.startswith("same reference")
    # new: half the problems, 6/8 of the time, mean 300 us, median 300, 5 iterations, one of two second starts
    assert n_val == "50.0 % / 75.0 %; 300 / 300; 5.00; 50.0 %"
    assert s_val == "50.0 % / 25.0 %; 100 / 100; 2.00; 0.0 %"
    rows = mod.split_rows(t, it, st, np.zeros(4, bool))
    assert rows[0] == ("new reference: no problems", "-")
