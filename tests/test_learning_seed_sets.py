"""The evaluation protocol's scenario seeds: fixed, and disjoint between every pair of sets."""
import itertools

import pytest

from bimacppo_learning.seed_sets import EVAL_SEED_BASE, SEED_SETS, eval_seed


def _cells(seed_set, episodes=1000):
    # every task, every N_sv a cell index can take (0..9), every episode index
    return {eval_seed(t, n, k, seed_set) for t in range(3) for n in range(10) for k in range(episodes)}


def test_test_seeds_are_fixed():
    seeds = {eval_seed(t, n, k) for t in range(3) for n in range(4) for k in range(100)}
    assert len(seeds) == 1200 and min(seeds) >= EVAL_SEED_BASE
    assert seeds <= _cells("test")
    assert eval_seed(1, 3, 7, "validation") == SEED_SETS["validation"] + 10_000 + 3_000 + 7


def test_every_pair_of_seed_sets_is_disjoint():
    """Choices never see a scenario that reports, and the second pair shares none with the first."""
    assert {"validation", "test", "validation2", "test2"} <= set(SEED_SETS)
    sets = {name: _cells(name) for name in SEED_SETS}
    assert all(len(s) == 30_000 for s in sets.values())
    for a, b in itertools.combinations(sets, 2):
        assert not sets[a] & sets[b], (a, b)


def test_out_of_range_index_and_unknown_set_are_refused():
    with pytest.raises(ValueError, match="at most 1000"):
        eval_seed(0, 0, 1000)
    with pytest.raises(ValueError, match="unknown seed set 'train'"):
        eval_seed(0, 0, 0, "train")


def test_every_command_offers_every_seed_set():
    from bimacppo_learning.cli import _eval_parser

    for name in SEED_SETS:
        assert _eval_parser().parse_args(["--seed-set", name]).seed_set == name
