"""scripts/failure_causes.py: an episode's final info names what the EV collided with, an EV
that cuts across the kerb counts as off the road (not as an SV collision), and the table counts
every episode of every task."""
import re

import numpy as np

from conftest import REPO, load_script


def _script():
    return load_script("failure_causes")


def test_a_kerb_crossing_is_off_road_and_an_sv_hit_names_the_sv():
    from bimacppo_common.conventions import TASKS
    from bimacppo_learning.env import IntersectionEnv
    from bimacppo_learning.evaluate import eval_seed

    mod = _script()
    # WP4 held at 2 m/s in the empty right turn, without the chord limit: across the kerb
    env = IntersectionEnv(config=REPO / "bimacppo_learning/bimacppo_learning/config/env_yield_far.yaml")
    right = TASKS.index("right")
    env.reset(options={"n_sv": 0, "task": right, "scenario_seed": eval_seed(right, 0, 0, "validation")})
    done = False
    while not done:
        _, _, term, trunc, info = env.step(np.array([4, 1, 1]))
        done = term or trunc
    assert info["outcome"] == "collision" and info["collided_with"] == "offroad"
    assert mod.cause_of(info) == "off road"
    assert mod.cause_of({"outcome": "collision", "collided_with": "sv1"}) == "sv collision"
    assert mod.cause_of({"outcome": "timeout", "collided_with": None}) == "timeout"
    env.close()


def test_the_table_counts_every_episode(capsys):
    assert _script().main(["--tasks", "left", "right", "--n-sv", "0", "--episodes", "2"]) == 0
    rows = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| left") or ln.startswith("| right")]
    assert [r.split("|")[1].strip() for r in rows] == ["left", "right"]
    for r in rows:
        counts = [int(x) for x in re.findall(r"\d+", r)]
        assert len(counts) == 4 and sum(counts) == 2
