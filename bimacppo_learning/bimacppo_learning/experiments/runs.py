"""What is already on disk: a run's history and status, its checkpoints, whether it was trained
with this config's settings, and whether a cached evaluation CSV still holds for the current
policy and protocol. Every step reads these to skip what is done and redo nothing that is.

A run counts as done when its history has the episode budget, ``policy.pt`` exists and its
settings (``experiment.json``, written when the grid starts it; else the ``run.json`` that
``bimacppo-train`` writes) match the config's: curriculum, seed, map, NMPC solver, env config
and PPO section. The budget is not a setting: raising ``episodes`` resumes finished runs.
A run directory with other settings is never overwritten: that run fails with the keys that
differ."""
from __future__ import annotations

import csv
import functools
import json
import os
from dataclasses import dataclass
from pathlib import Path

from bimacppo_common.conventions import OUTCOMES, TASKS

from .config import ExperimentConfig, ExperimentError


def read_history(run_dir: str | os.PathLike) -> list[dict]:
    """All episode records of a run. A partial *last* line (a run killed mid-write) is dropped;
    anything else unreadable is a corrupt history, reported with file and line."""
    path = Path(run_dir) / "history.jsonl"
    if not path.is_file():
        raise ExperimentError(f"{path}: no history.jsonl (is {run_dir} a bimacppo-train run directory?)")
    lines = path.read_text().splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    recs: list[dict] = []
    for k, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            if k == len(lines):
                break
            raise ExperimentError(f"corrupt history {path}:{k}: not JSON") from None
        if not isinstance(rec, dict) or not isinstance(rec.get("episode"), int) or rec.get("outcome") not in OUTCOMES:
            raise ExperimentError(f"corrupt history {path}:{k}: a record needs an integer 'episode' and an "
                                  f"'outcome' in {OUTCOMES}")
        if recs and rec["episode"] != recs[-1]["episode"] + 1:
            raise ExperimentError(f"corrupt history {path}:{k}: episode {rec['episode']} follows "
                                  f"{recs[-1]['episode']}")
        recs.append(rec)
    return recs


def last_episode(run_dir: str | os.PathLike) -> int:
    """Episodes recorded so far, read from the end of history.jsonl (cheap enough to poll)."""
    path = Path(run_dir) / "history.jsonl"
    try:
        with path.open("rb") as fh:
            fh.seek(0, os.SEEK_END)
            fh.seek(max(0, fh.tell() - 65536))
            tail = fh.read().decode("utf-8", "replace").splitlines()
    except OSError:
        return 0
    for line in reversed(tail):
        try:
            return int(json.loads(line)["episode"])
        except (ValueError, KeyError, TypeError):
            continue
    return 0


def has_checkpoint(run_dir: str | os.PathLike) -> bool:
    from ..checkpoint import latest_checkpoint

    d = Path(run_dir) / "checkpoints"
    return d.is_dir() and latest_checkpoint(d) is not None


SETTINGS_FILE = "experiment.json"
#: the keys of run.json (bimacppo-train's record) that are settings, for runs without experiment.json
RUN_JSON_KEYS = ("curriculum", "seed", "map", "mpc", "env_config")


@functools.lru_cache(maxsize=16)
def _shared_settings(env_config: str | None, ppo_config: str | None, stamp: tuple) -> str:
    from bimacppo_planner.decision import ConfigError, EnvConfig

    from ..ppo_config import config_to_dict, load_config

    try:
        env = EnvConfig.load(env_config).to_dict()
        pcfg, _ = load_config(ppo_config)
    except (ConfigError, ValueError, OSError) as exc:
        raise ExperimentError(str(exc)) from None
    return json.dumps({"env_config": env, "ppo": config_to_dict(pcfg)["ppo"]})


def _mtime(path: str | None) -> int | None:
    try:
        return None if path is None else os.stat(path).st_mtime_ns
    except OSError:
        return None


def run_settings(cfg: ExperimentConfig, method: str, seed: int) -> dict:
    """What a run of this grid is trained with (JSON types), as compared with what is on disk."""
    t = cfg.train
    shared = json.loads(_shared_settings(t.env_config, t.ppo_config, (_mtime(t.env_config), _mtime(t.ppo_config))))
    return {"curriculum": method, "seed": seed, "map": cfg.train_map, "mpc": t.mpc, **shared}


def settings_mismatch(run_dir: str | os.PathLike, expected: dict) -> list[str]:
    """The setting keys whose recorded value differs from ``expected`` (empty: nothing recorded
    yet, or everything matches)."""
    d = Path(run_dir)
    for name, keys in ((SETTINGS_FILE, tuple(expected)), ("run.json", RUN_JSON_KEYS)):
        try:
            have = json.loads((d / name).read_text())
        except (OSError, ValueError):
            continue
        if not isinstance(have, dict):
            return [f"{name} is not a JSON object"]
        return [k for k in keys if k in expected and have.get(k) != expected[k]]
    return []


def write_settings(run_dir: str | os.PathLike, settings: dict) -> None:
    d = Path(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    tmp = d / f".{SETTINGS_FILE}.tmp"
    tmp.write_text(json.dumps(settings, indent=2, sort_keys=True))
    os.replace(tmp, d / SETTINGS_FILE)


@dataclass(frozen=True)
class RunStatus:
    method: str
    seed: int
    run_dir: Path
    episodes: int          # recorded in history.jsonl
    budget: int
    mismatch: tuple = ()   # setting keys that differ from the config's

    @property
    def done(self) -> bool:
        return not self.mismatch and self.episodes >= self.budget and (self.run_dir / "policy.pt").is_file()

    @property
    def state(self) -> str:
        if self.mismatch:
            return "other settings"
        if self.done:
            return "done"
        return "partial" if self.episodes or self.run_dir.exists() else "missing"


def run_status(cfg: ExperimentConfig, method: str, seed: int) -> RunStatus:
    d = cfg.run_dir(method, seed)
    mismatch = tuple(settings_mismatch(d, run_settings(cfg, method, seed))) if d.is_dir() else ()
    return RunStatus(method, seed, d, last_episode(d), cfg.episodes, mismatch)


def read_eval_csv(path: str | os.PathLike) -> dict[tuple[int, int], tuple[float, float, float, int]]:
    """(task index, N_sv) -> (success %, collision %, timeout %, episodes) from an evaluation CSV."""
    path = Path(path)
    out = {}
    try:
        with path.open() as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise ExperimentError(f"{path}: cannot read evaluation CSV: {exc.strerror or exc}") from None
    for k, row in enumerate(rows, 2):
        try:
            key = (TASKS.index(row["task"]), int(row["n_sv"]))
            vals = (float(row["success_pct"]), float(row["collision_pct"]), float(row["timeout_pct"]),
                    int(row["episodes"]))
        except (KeyError, ValueError, TypeError) as exc:
            raise ExperimentError(f"{path}:{k}: malformed evaluation row ({type(exc).__name__}: {exc})") from None
        if not all(0.0 <= v <= 100.0 for v in vals[:3]):
            raise ExperimentError(f"{path}:{k}: percentages out of 0..100")
        out[key] = vals
    if not out:
        raise ExperimentError(f"{path}: no evaluation rows")
    return out


def protocol_cells(cfg: ExperimentConfig) -> set[tuple[int, int]]:
    return {(TASKS.index(t), n) for t in cfg.evaluation.tasks for n in cfg.evaluation.n_sv}


def eval_is_fresh(cfg: ExperimentConfig, csv_path: Path, policy_path: Path | None) -> bool:
    """A cached CSV counts if it is newer than the policy and ran this config's protocol."""
    if not csv_path.is_file():
        return False
    if policy_path is not None and csv_path.stat().st_mtime <= policy_path.stat().st_mtime:
        return False
    try:
        cells = read_eval_csv(csv_path)
    except ExperimentError:
        return False
    return set(cells) == protocol_cells(cfg) and all(v[3] == cfg.evaluation.episodes for v in cells.values())
