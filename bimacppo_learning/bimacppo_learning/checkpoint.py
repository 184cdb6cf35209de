"""Training checkpoints and the policy-only export (read back by ``bimacppo_planner.policy``).

Every file is read with ``torch.load(..., weights_only=True)`` (no arbitrary unpickling), so
payloads hold only tensors and plain Python types; the scheduler state travels as JSON text.
Writes are atomic (temp file in the same directory, fsync, ``os.replace``): a crash mid-write
leaves the previous file intact.  Any unreadable, truncated, foreign or mis-shaped file raises
``CheckpointError`` naming the file and the problem.
"""
from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import re
import tempfile
from typing import Any, Mapping

import torch

from bimacppo_planner.policy import (CHECKPOINT_FORMAT, FORMAT_VERSION, POLICY_FORMAT,  # noqa: F401
                                     CheckpointError, Policy, check_normaliser, read_torch_file,
                                     require_finite_weights, require_keys)

CKPT_PATTERN = re.compile(r"^ckpt_ep(\d+)\.pt$")

_CKPT_KEYS = ("format", "version", "agent", "config", "scheduler_state", "counters", "rng")
_AGENT_KEYS = ("obs_dim", "nvec", "actor", "critic", "actor_opt", "critic_opt", "obs_rms", "gen")


def atomic_torch_save(obj: Any, path: str | os.PathLike) -> None:
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def save_checkpoint(path: str | os.PathLike, payload: Mapping[str, Any]) -> None:
    """Atomically write a training checkpoint (payload built by the Trainer)."""
    require_keys(path, payload, _CKPT_KEYS, "checkpoint payload", CHECKPOINT_FORMAT)
    atomic_torch_save(dict(payload), path)


def load_checkpoint(path: str | os.PathLike) -> dict:
    """Read and structurally validate a training checkpoint (shapes are checked on restore)."""
    return check_checkpoint(read_torch_file(path), path)


def check_checkpoint(d: Any, path: str | os.PathLike) -> dict:
    """``d``, the content of ``path``, if it is a training checkpoint this code reads; else
    CheckpointError naming ``path`` and the problem."""
    require_keys(path, d, _CKPT_KEYS, "checkpoint", CHECKPOINT_FORMAT)
    if d["version"] != FORMAT_VERSION:
        raise CheckpointError(path, f"format version {d['version']!r}, this code reads {FORMAT_VERSION}")
    agent = d["agent"]
    require_keys(path, agent, _AGENT_KEYS, "checkpoint['agent']", CHECKPOINT_FORMAT)
    for net in ("actor", "critic"):
        require_finite_weights(path, agent[net], net)
    if isinstance(agent["obs_rms"], Mapping):
        check_normaliser(path, agent["obs_rms"])
    return d


def fine_tune_source_record(path: str | os.PathLike, meta: Mapping[str, Any]) -> dict:
    """What a fine-tune records of the file it started from (run metadata ``fine_tuned_from``,
    kept in its checkpoints and exported policy): the file's name and SHA-256, the source's
    curriculum, map, seed and episodes, and the source's own ``fine_tuned_from``. So a policy
    file states its whole lineage, e.g. that a 9,000-episode fine-tune started from an
    18,000-episode fine-tune of a 7,500-episode run, and each step names the exact bytes it
    started from. ``meta`` is the source's run metadata (with ``episodes``)."""
    import hashlib

    path = pathlib.Path(path)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    record = {"file": path.name, "sha256": digest}
    for key in ("curriculum", "map", "seed", "episodes"):
        if meta.get(key) is not None:
            record[key] = meta[key]
    if meta.get("fine_tuned_from") is not None:
        record["fine_tuned_from"] = meta["fine_tuned_from"]
    return record


def restore_agent(agent, state: Mapping[str, Any], path: str | os.PathLike) -> None:
    """Load ``state`` into ``agent``; a dimension or tensor-shape mismatch -> CheckpointError."""
    try:
        agent.load_state_dict(state)
    except (ValueError, KeyError, RuntimeError, TypeError) as exc:
        raise CheckpointError(path, f"does not fit this agent: {exc}") from None


def run_meta_of(d: Mapping[str, Any], path: str | os.PathLike) -> dict:
    """How the run that wrote checkpoint ``d`` was set up (the Trainer's ``run_meta``, stored as
    JSON under "run"); {} for a checkpoint written without it."""
    raw = d.get("run")
    if raw is None or raw == "":
        return {}
    try:
        meta = json.loads(raw) if isinstance(raw, (str, bytes)) else raw
    except ValueError as exc:
        raise CheckpointError(path, f"run metadata is not valid JSON: {exc}") from None
    if not isinstance(meta, Mapping):
        raise CheckpointError(path, f"run metadata is a {type(meta).__name__}, expected a dict")
    return dict(meta)


def checkpoint_meta(d: Mapping[str, Any], path: str | os.PathLike) -> dict:
    """A checkpoint's run metadata with its ``episodes`` (from its counters; left out when they
    are unreadable), the fields a policy export's metadata carries: what a fine-tune records of
    its source."""
    meta = run_meta_of(d, path)
    try:
        meta.setdefault("episodes", int(d["counters"]["episodes"]))
    except (KeyError, TypeError, ValueError):
        pass
    return meta


def mpc_config_of(meta: Mapping[str, Any], path: str | os.PathLike):
    """The NMPC config a run was trained with (its run metadata's ``mpc_config``, read as a record:
    a key added since takes the value that reproduces the controller before it, see
    ``MPCConfig.from_record``), or None when
    the metadata records none (a file written before runs recorded it: the controller is unknown).
    A recorded config that is no longer valid is a CheckpointError naming the file and key."""
    raw = meta.get("mpc_config")
    if raw is None:
        return None
    from bimacppo_mpc import MPCConfig

    try:
        cfg = MPCConfig.from_record(raw, source="mpc_config")
    except ValueError as exc:      # "<path>: run metadata mpc_config: key 'horizon' must be ..."
        raise CheckpointError(path, f"run metadata {exc}") from None
    return dataclasses.replace(cfg, source=f"{path} (run mpc_config)")


def config_differences(saved: Any, current: Any, prefix: str = "") -> list[str]:
    """``"section.key: saved != current"`` for every leaf where two nested config dicts differ
    (a key on one side only shows ``<absent>`` on the other), in key order."""
    if isinstance(saved, Mapping) and isinstance(current, Mapping):
        out = []
        for k in sorted(set(saved) | set(current), key=str):
            name = f"{prefix}.{k}" if prefix else str(k)
            if k not in saved or k not in current:
                a = saved[k] if k in saved else "<absent>"
                b = current[k] if k in current else "<absent>"
                out.append(f"{name}: {a} != {b}")
            else:
                out += config_differences(saved[k], current[k], name)
        return out
    return [] if saved == current else [f"{prefix}: {saved} != {current}"]


def checkpoint_path(directory: str | os.PathLike, episodes: int) -> pathlib.Path:
    return pathlib.Path(directory) / f"ckpt_ep{episodes:08d}.pt"


def list_checkpoints_by_episodes(directory: str | os.PathLike) -> list[tuple[int, pathlib.Path]]:
    """(episodes, path) of the checkpoint files in ``directory``, oldest (fewest episodes) first."""
    d = pathlib.Path(directory)
    if not d.is_dir():
        return []
    return sorted((int(m.group(1)), p) for p in d.iterdir() if (m := CKPT_PATTERN.match(p.name)))


def list_checkpoints(directory: str | os.PathLike) -> list[pathlib.Path]:
    """Checkpoint files in ``directory``, oldest (fewest episodes) first."""
    return [p for _, p in list_checkpoints_by_episodes(directory)]


def latest_checkpoint(directory: str | os.PathLike) -> pathlib.Path | None:
    cks = list_checkpoints(directory)
    return cks[-1] if cks else None


# ------------------------------------------------------------------ deployment
def export_policy(agent, path: str | os.PathLike, meta: Mapping[str, Any] | None = None) -> pathlib.Path:
    """Write the actor + observation normaliser + metadata: all a planner node needs to act."""
    from .ppo_config import config_hash

    payload = {
        "format": POLICY_FORMAT,
        "version": FORMAT_VERSION,
        "actor": {k: v.detach().clone() for k, v in agent.actor.state_dict().items()},
        "obs_rms": agent.obs_rms.state_dict(),
        "obs_dim": int(agent.obs_dim),
        "nvec": [int(n) for n in agent.nvec],
        "hidden_sizes": [int(h) for h in agent.cfg.hidden_sizes],
        "activation": agent.cfg.activation,
        "obs_norm": bool(agent.cfg.obs_norm),
        "config_hash": config_hash(agent.cfg),
        "meta": dict(meta or {}),
    }
    atomic_torch_save(payload, path)
    return pathlib.Path(path)




def _new_policy_file(dst: str | os.PathLike, selection: str) -> pathlib.Path:
    """``dst`` as a path for a new policy file that acts by ``selection``: ValueError for a
    selection that is not deterministic, FileExistsError for a file that exists (a policy file is
    never overwritten)."""
    from bimacppo_planner.policy import DEPLOYED_SELECTIONS

    if selection not in DEPLOYED_SELECTIONS:
        raise ValueError(f"action selection must be one of {DEPLOYED_SELECTIONS}, got {selection!r}")
    dst = pathlib.Path(dst)
    if dst.exists():
        raise FileExistsError(f"{dst}: exists; a policy file is not overwritten")
    return dst


def set_action_selection(src: str | os.PathLike, dst: str | os.PathLike, selection: str,
                         meta: Mapping[str, Any] | None = None) -> pathlib.Path:
    """Write ``src`` (a policy export or a training checkpoint) to ``dst`` as a policy export
    that records ``selection`` as the way it acts when deployed (``Policy.selection``: the
    planner and ``bimacppo-evaluate`` then run it so unless told otherwise), and ``meta``'s
    entries beside the source's own metadata. The actor and normaliser are copied unchanged. ``dst`` must not exist (FileExistsError): a policy file is
    never overwritten. ValueError for a selection that is not deterministic."""
    from bimacppo_planner.policy import read_policy_payload

    dst = _new_policy_file(dst, selection)
    d = read_policy_payload(src)
    Policy(d, src)   # refuses anything that is not a usable policy, naming src
    payload = {**d, "meta": {**dict(d["meta"]), **dict(meta or {}), "action_selection": selection}}
    atomic_torch_save(payload, dst)
    return dst


def make_ensemble(members, dst: str | os.PathLike, selection: str = "median",
                  combine: str = "mixture") -> pathlib.Path:
    """Write ``members`` (policy exports or training checkpoints, at least 2, trained alike) to
    ``dst`` as one ensemble policy file (``bimacppo_planner.policy.EnsemblePolicy``: each head acts
    on the mixture of the members' distributions, or by their vote with ``combine="vote"``) that
    records ``selection`` as the way it acts when deployed. The metadata lists each member's file,
    training seed and budget. ``dst`` must not exist (FileExistsError); CheckpointError names a
    member that is unreadable, an ensemble itself, or trained with another observation, decoding
    or NMPC than the first."""
    from bimacppo_planner.policy import ENSEMBLE_COMBINES, ENSEMBLE_FORMAT, EnsemblePolicy, read_policy_payload

    dst = _new_policy_file(dst, selection)
    if combine not in ENSEMBLE_COMBINES:
        raise ValueError(f"combine must be one of {ENSEMBLE_COMBINES}, got {combine!r}")
    payloads, listed = [], []
    for src in members:
        d = read_policy_payload(src)
        if isinstance(d, Mapping) and d.get("format") == ENSEMBLE_FORMAT:
            raise CheckpointError(src, "is an ensemble; list its members instead")
        Policy(d, src)   # refuses anything that is not a usable policy, naming src
        payloads.append(dict(d))
        listed.append({"file": str(src), "seed": d["meta"].get("seed"), "episodes": d["meta"].get("episodes")})
    meta = {"members": listed, "combine": combine, "action_selection": selection}
    payload = {"format": ENSEMBLE_FORMAT, "version": FORMAT_VERSION, "members": payloads, "meta": meta}
    EnsemblePolicy(payload, dst)   # the members fit together, or CheckpointError before writing
    atomic_torch_save(payload, dst)
    return dst
