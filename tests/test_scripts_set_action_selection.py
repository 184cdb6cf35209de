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


def test_the_copy_can_record_the_file_its_run_started_from(tmp_path, capsys):
    """--fine-tuned-from SOURCE records SOURCE's name, SHA-256, seed and episodes (what
    bimacppo-train --init-policy records) with the selection; a policy that records a lineage
    already, or a source that is no policy, is one error line and nothing is written."""
    import hashlib

    cfg = EnvConfig.load()
    source = export_policy(PPO(cfg.obs_dim, cfg.nvec, seed=2), tmp_path / "source.pt",
                           meta={"seed": 2, "episodes": 18000, "curriculum": "bimab", "map": "three_lane_straight"})
    src = export_policy(PPO(cfg.obs_dim, cfg.nvec, seed=1), tmp_path / "p.pt", meta={"seed": 0, "episodes": 9000})
    mod = _script()
    assert mod.main([str(src), str(tmp_path / "m.pt"), "--action", "median", "--fine-tuned-from", str(source)]) == 0
    rec = load_policy(tmp_path / "m.pt").meta["fine_tuned_from"]
    assert rec == {"file": "source.pt", "sha256": hashlib.sha256(source.read_bytes()).hexdigest(),
                   "curriculum": "bimab", "map": "three_lane_straight", "seed": 2, "episodes": 18000}
    capsys.readouterr()
    assert mod.main([str(tmp_path / "m.pt"), str(tmp_path / "n.pt"), "--action", "median",
                     "--fine-tuned-from", str(source)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "fine-tuned from already" in err[0] and not (tmp_path / "n.pt").exists()
    (tmp_path / "junk.pt").write_bytes(b"junk")
    assert mod.main([str(src), str(tmp_path / "n.pt"), "--action", "median", "--fine-tuned-from",
                     str(tmp_path / "junk.pt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "junk.pt" in err[0] and not (tmp_path / "n.pt").exists()
