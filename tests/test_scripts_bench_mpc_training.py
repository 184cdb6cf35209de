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
                  "1 / 2 threads", "ratio 2 threads", "peak RSS"):
        assert label in out, label
