"""scripts/set_action_selection.py: a copy of a policy file that records how it acts, the
source untouched, and one error line (exit 2) for an existing output or an unusable source."""

import numpy as np

from conftest import load_script
from bimacppo_learning.checkpoint import export_policy
from bimacppo_learning.ppo import PPO
from bimacppo_planner.agent import load_policy
from bimacppo_planner.decision import EnvConfig


def _script():
    return load_script("set_action_selection")


def test_the_copy_records_the_selection_and_keeps_the_weights(tmp_path, capsys):
    cfg = EnvConfig.load()
    src = export_policy(PPO(cfg.obs_dim, cfg.nvec, seed=1), tmp_path / "p.pt", meta={"seed": 1})
    before = src.read_bytes()
    mod = _script()
    assert mod.main([str(src), str(tmp_path / "m.pt"), "--action", "median"]) == 0
    assert "acts by median" in capsys.readouterr().out
    a, b = load_policy(src), load_policy(tmp_path / "m.pt")
    assert (a.selection, b.selection) == ("argmax", "median") and b.meta["seed"] == 1
    obs = np.random.default_rng(0).normal(size=a.obs_dim)
    np.testing.assert_array_equal(a.logits(obs)[1], b.logits(obs)[1])
    assert src.read_bytes() == before
    assert mod.main([str(src), str(tmp_path / "m.pt"), "--action", "argmax"]) == 2
    assert "exists" in capsys.readouterr().err
    (tmp_path / "junk.pt").write_bytes(b"junk")
    assert mod.main([str(tmp_path / "junk.pt"), str(tmp_path / "j.pt"), "--action", "median"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "junk.pt" in err[0] and not (tmp_path / "j.pt").exists()
