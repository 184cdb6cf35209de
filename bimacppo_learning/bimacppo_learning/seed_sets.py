"""The evaluation protocol's scenario seeds, kept apart from ``evaluate`` so that command-line
parsers can list the seed sets without importing torch.

Every method is evaluated on exactly the same scenarios: the scenario seed of episode k
in cell (task j, N_sv i) is ``base + 10_000*j + 1_000*i + k``, far away from the seeds
training draws (those come from the training RNG, uniformly in [0, 2^31)). The seed sets
(``SEED_SETS``) are disjoint: ``validation``, for every choice (config, checkpoint, variant),
and ``test``, only ever reported. ``validation2`` and ``test2`` are a second such pair, for a
choice that has to be made again once the first pair's readings of the candidates are all
known: a validation set that has chosen many times favours what it chose, and the test set's
readings were seen. The second pair chooses and reports afresh; the first pair's readings
stay reported. A cell holds at most 1,000 scenarios per set, so more scenarios for a choice
need another set rather than a higher index.
"""
from __future__ import annotations

EVAL_SEED_BASE = 1_000_000          # the test set
SEED_SETS = {"test": EVAL_SEED_BASE, "validation": 2_000_000, "test2": 3_000_000, "validation2": 4_000_000}
CHOOSING_SETS = ("validation", "validation2")   # the sets a choice may read; the others only report


def eval_seed(task: int, n_sv: int, k: int, seed_set: str = "test") -> int:
    if not (0 <= k < 1_000):
        raise ValueError(f"episode index {k} out of range: at most 1000 evaluation episodes per cell")
    if seed_set not in SEED_SETS:
        raise ValueError(f"unknown seed set {seed_set!r}; expected one of {sorted(SEED_SETS)}")
    return SEED_SETS[seed_set] + 10_000 * task + 1_000 * n_sv + k
