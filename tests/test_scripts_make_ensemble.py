"""scripts/make_ensemble.py: an ensemble file from policy files trained alike, and one error line
(exit 2) for an existing output or a member that does not fit."""

from conftest import load_script
from bimacppo_learning.checkpoint import export_policy
from bimacppo_learning.ppo import PPO
from bimacppo_planner.agent import load_policy
from bimacppo_planner.decision import EnvConfig
from bimacppo_planner.policy import EnsemblePolicy


def test_the_script_writes_an_ensemble_and_refuses_in_one_line(tmp_path, capsys):
    cfg = EnvConfig.load()
    a, b = (export_policy(PPO(cfg.obs_dim, cfg.nvec, seed=s), tmp_path / f"p{s}.pt", meta={"seed": s})
            for s in (1, 2))
    mod = load_script("make_ensemble")
    assert mod.main([str(tmp_path / "e.pt"), str(a), str(b)]) == 0
    assert "2 members" in capsys.readouterr().out
    e = load_policy(tmp_path / "e.pt")
    assert isinstance(e, EnsemblePolicy) and e.selection == "median" and len(e.members) == 2
    assert mod.main([str(tmp_path / "e.pt"), str(a), str(b)]) == 2
    assert "exists" in capsys.readouterr().err
    c = export_policy(PPO(cfg.obs_dim + 2, cfg.nvec, seed=3), tmp_path / "c.pt")
    assert mod.main([str(tmp_path / "f.pt"), str(a), str(c)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "member 1" in err[0] and not (tmp_path / "f.pt").exists()
