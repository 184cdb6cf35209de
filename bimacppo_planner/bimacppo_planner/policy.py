"""Policy files for deployment: the on-disk formats, ``CheckpointError`` and ``Policy``.

The deployed planner needs only this module (numpy inference, ``torch.load`` to read), never the
training stack. Every file is read with ``torch.load(..., weights_only=True)`` (no arbitrary
unpickling), so payloads hold only tensors and plain Python types. Any unreadable, truncated,
foreign or mis-shaped file raises ``CheckpointError`` naming the file and the problem.

Three formats are read: the policy export (actor + observation normaliser + metadata, what
training writes as ``policy.pt``), an ensemble of such exports that acts as one policy
(``EnsemblePolicy``) and, for convenience, a full training checkpoint, whose actor and normaliser
are taken out of the agent state.
"""
from __future__ import annotations

import json
import math
import os
import pathlib
from typing import Any, Mapping

import numpy as np
import torch

CHECKPOINT_FORMAT = "bimacppo-ppo-checkpoint"
POLICY_FORMAT = "bimacppo-ppo-policy"
ENSEMBLE_FORMAT = "bimacppo-ppo-ensemble"
FORMAT_VERSION = 1

#: deterministic selections, the ones a policy file may name as its own and a planner may run
DEPLOYED_SELECTIONS = ("argmax", "median")

POLICY_KEYS = ("format", "version", "actor", "obs_rms", "obs_dim", "nvec", "hidden_sizes",
               "activation", "obs_norm", "config_hash", "meta")
ENSEMBLE_KEYS = ("format", "version", "members", "meta")
#: metadata every member of an ensemble must record alike: what the policy observes and how its
#: actions are decoded (``env_config``), the controller that follows them, and the road
ENSEMBLE_SHARED_META = ("env_config", "mpc_config", "mpc", "map")
#: how an ensemble's deterministic actions combine its members (``EnsemblePolicy``)
ENSEMBLE_COMBINES = ("mixture", "vote")


class CheckpointError(Exception):
    """A checkpoint or policy file that cannot be used; the message names the file."""

    def __init__(self, path: str | os.PathLike, problem: str = "cannot be used"):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):
        # crosses process boundaries (evaluation workers) with both arguments intact
        return (type(self), (self.path, self.problem))


def read_torch_file(path: str | os.PathLike) -> Any:
    """``torch.load(weights_only=True)`` of ``path``; any failure -> CheckpointError."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise CheckpointError(path, "is a directory, not a file" if path.is_dir() else "no such file")
    if path.stat().st_size == 0:
        raise CheckpointError(path, "file is empty (truncated write?)")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises RuntimeError/UnpicklingError/EOFError/... by cause
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(path, f"not a readable torch file (corrupt or truncated): "
                                    f"{type(exc).__name__}: {msg[:200]}") from None


def require_keys(path, d: Any, keys, what: str, fmt: str) -> None:
    """``d`` is a dict of format ``fmt`` holding ``keys``, else CheckpointError."""
    if not isinstance(d, Mapping):
        raise CheckpointError(path, f"{what} is a {type(d).__name__}, expected a dict")
    if d.get("format", fmt) != fmt:
        raise CheckpointError(path, f"format {d.get('format')!r}, expected {fmt!r}")
    missing = [k for k in keys if k not in d]
    if missing:
        raise CheckpointError(path, f"{what} lacks key(s) {missing}")


def require_finite(path, tensors: Mapping[str, Any], what: str) -> None:
    """Every tensor or array in ``tensors`` is finite, else CheckpointError naming the first that
    is not: a NaN or inf weight makes every action the same (the argmax of NaN logits is 0)
    without an error, so a file holding one is refused as corrupt when it is read."""
    for name, t in tensors.items():
        try:
            a = t.detach().cpu().numpy() if isinstance(t, torch.Tensor) else np.asarray(t, np.float64)
            finite = np.all(np.isfinite(a))
        except (TypeError, ValueError):
            raise CheckpointError(path, f"{what}.{name} is a {type(t).__name__}, not numbers: the file is "
                                        "corrupt") from None
        if not finite:
            raise CheckpointError(path, f"{what}.{name} holds {int(np.size(a) - np.isfinite(a).sum())} "
                                        "non-finite value(s) (NaN or inf): the file is corrupt")


def require_finite_weights(path, state: Any, what: str) -> None:
    """``require_finite`` over the tensors of a network's state dict ``state`` (named ``what``);
    a state that is not a mapping is left to the shape checks that follow."""
    if isinstance(state, Mapping):
        require_finite(path, {k: v for k, v in state.items() if isinstance(v, torch.Tensor)}, what)


def check_normaliser(path, rms: Mapping[str, Any]) -> None:
    """The observation normaliser's statistics can normalise: finite mean, a finite variance
    that is not negative, finite eps >= 0, clip > 0 and count >= 0; else CheckpointError naming
    the entry. A negative variance or a NaN clip turns every observation into NaN, and every
    action into argmax 0, without an error."""
    require_finite(path, {k: rms[k] for k in ("mean", "var", "eps", "clip", "count") if k in rms}, "obs_rms")
    var = rms.get("var")
    if var is not None and np.any(np.asarray(var, np.float64) < 0.0):
        raise CheckpointError(path, "obs_rms.var holds negative variances: the file is corrupt")
    for key, low, strict in (("eps", 0.0, False), ("clip", 0.0, True), ("count", 0.0, False)):
        if key in rms and (float(rms[key]) <= low if strict else float(rms[key]) < low):
            raise CheckpointError(path, f"obs_rms.{key} = {float(rms[key])!r} must be "
                                        f"{'>' if strict else '>='} {low:g}: the file is corrupt")


def policy_payload_of_checkpoint(d: Mapping[str, Any], path: str | os.PathLike) -> dict:
    """The policy export held inside a training checkpoint (its actor, normaliser, PPO sizes)."""
    try:
        agent, ppo = d["agent"], d["config"]["ppo"]
        return {"format": POLICY_FORMAT, "version": d["version"], "actor": agent["actor"],
                "obs_rms": agent["obs_rms"], "obs_dim": int(agent["obs_dim"]),
                "nvec": [int(n) for n in agent["nvec"]],
                "hidden_sizes": [int(h) for h in ppo["hidden_sizes"]],
                "activation": str(ppo["activation"]), "obs_norm": bool(ppo["obs_norm"]),
                "config_hash": "", "meta": json.loads(d.get("run") or "{}")}
    except (KeyError, TypeError, ValueError) as exc:  # json.JSONDecodeError is a ValueError
        raise CheckpointError(path, f"training checkpoint lacks the actor: {type(exc).__name__}: {exc}") from None


def read_policy_payload(path: str | os.PathLike) -> Any:
    """What ``path`` holds as a policy file: a training checkpoint's policy export (its actor and
    normaliser), else the file's content as read (an export, an ensemble, or anything else, which
    the reader refuses). CheckpointError for an unreadable file."""
    d = read_torch_file(path)
    if isinstance(d, Mapping) and d.get("format") == CHECKPOINT_FORMAT:
        d = policy_payload_of_checkpoint(d, path)
    return d


class Policy:
    """Deployed policy: single-observation inference in plain numpy (no autograd, no batching
    overhead), bit-for-bit the same argmax as the training actor."""

    def __init__(self, payload: Mapping[str, Any], path: str | os.PathLike = "<memory>"):
        require_keys(path, payload, POLICY_KEYS, "policy file", POLICY_FORMAT)
        if payload["version"] != FORMAT_VERSION:
            raise CheckpointError(path, f"format version {payload['version']!r}, this code reads {FORMAT_VERSION}")
        self.path = str(path)
        self.obs_dim = int(payload["obs_dim"])
        self.nvec = tuple(int(n) for n in payload["nvec"])
        self.hidden_sizes = tuple(int(h) for h in payload["hidden_sizes"])
        self.activation = str(payload["activation"])
        if self.activation not in ("tanh", "relu"):
            raise CheckpointError(path, f"unknown activation {self.activation!r}")
        self.obs_norm = bool(payload["obs_norm"])
        self.config_hash = str(payload["config_hash"])
        self.meta = dict(payload["meta"])
        #: how the policy is meant to act when deployed (its metadata ``action_selection``, set
        #: for the policy that was chosen acting by it): one of DEPLOYED_SELECTIONS
        self.selection = str(self.meta.get("action_selection", "argmax"))
        if self.selection not in DEPLOYED_SELECTIONS:
            raise CheckpointError(path, f"metadata action_selection {self.selection!r} is not one of "
                                        f"{DEPLOYED_SELECTIONS}")
        sizes = [self.obs_dim, *self.hidden_sizes, sum(self.nvec)]
        actor = payload["actor"]
        require_finite_weights(path, actor, "actor")
        self.layers: list[tuple[np.ndarray, np.ndarray]] = []
        for k in range(len(sizes) - 1):
            wk, bk = f"{2 * k}.weight", f"{2 * k}.bias"
            if wk not in actor or bk not in actor:
                raise CheckpointError(path, f"actor lacks layer tensors {wk}/{bk}")
            w = actor[wk].detach().cpu().numpy().astype(np.float32)
            b = actor[bk].detach().cpu().numpy().astype(np.float32)
            if w.shape != (sizes[k + 1], sizes[k]) or b.shape != (sizes[k + 1],):
                raise CheckpointError(path, f"actor.{wk} has shape {w.shape}, bias {b.shape}; expected "
                                            f"({sizes[k + 1]}, {sizes[k]}) and ({sizes[k + 1]},)")
            self.layers.append((np.ascontiguousarray(w.T), b))
        if len(actor) != 2 * len(self.layers):
            raise CheckpointError(path, f"actor has {len(actor)} tensors, expected {2 * len(self.layers)}")
        rms = payload["obs_rms"]
        if isinstance(rms, Mapping):
            check_normaliser(path, rms)
        try:
            self.mean = np.asarray(rms["mean"], np.float64)
            self.std = np.sqrt(np.asarray(rms["var"], np.float64) + float(rms["eps"]))
            self.clip = float(rms["clip"])
            self.count = float(rms["count"])
        except (KeyError, TypeError) as exc:
            raise CheckpointError(path, f"obs normaliser is malformed: {exc}") from None
        if self.mean.shape != (self.obs_dim,) or self.std.shape != (self.obs_dim,):
            raise CheckpointError(path, f"obs normaliser shape {self.mean.shape} != ({self.obs_dim},)")
        self._split = np.cumsum(self.nvec)[:-1]
        self._act = np.tanh if self.activation == "tanh" else (lambda x: np.maximum(x, 0.0))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Policy":
        """A policy export, an ensemble of them (an ``EnsemblePolicy``) or a full training
        checkpoint (its actor and normaliser)."""
        d = read_policy_payload(path)
        if isinstance(d, Mapping) and d.get("format") == ENSEMBLE_FORMAT:
            return EnsemblePolicy(d, path)
        return cls(d, path)

    def logits(self, obs: np.ndarray) -> list[np.ndarray]:
        x = np.asarray(obs, np.float64)
        if x.shape != (self.obs_dim,):
            raise ValueError(f"observation must have shape ({self.obs_dim},), got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError("observation contains NaN or inf")
        if self.obs_norm and self.count > 0:
            x = np.clip((x - self.mean) / self.std, -self.clip, self.clip)
        elif self.obs_norm:
            x = np.clip(x, -self.clip, self.clip)
        h = x.astype(np.float32)
        for k, (w, b) in enumerate(self.layers):
            h = h @ w + b
            if k < len(self.layers) - 1:
                h = self._act(h)
        return np.split(h, self._split)

    def act(self, obs: np.ndarray, deterministic: bool = True,
            rng: np.random.Generator | None = None) -> np.ndarray:
        """One observation (obs_dim,) -> action (len(nvec),) int64: argmax per head, or a sample."""
        heads = self.logits(obs)
        if deterministic:
            return np.array([int(np.argmax(h)) for h in heads], np.int64)
        rng = rng if rng is not None else np.random.default_rng()
        out = []
        for h in heads:
            p = np.exp(h - h.max())
            out.append(int(rng.choice(len(p), p=p / p.sum())))
        return np.array(out, np.int64)


    def act_median(self, obs: np.ndarray) -> np.ndarray:
        """One observation -> action: each head's weighted median (see ``head_median``)."""
        return np.array([head_median(h) for h in self.logits(obs)], np.int64)


class EnsemblePolicy(Policy):
    """Several policies trained alike (the same env config, decoding and NMPC; other training
    seeds) acting as one. Each head's distribution is the mixture, the mean of the members'
    distributions, and ``logits`` returns its log-probabilities, so sampling acts on the mixture.
    The deterministic actions (argmax, median) follow the file's ``meta["combine"]``:

    * ``mixture`` (the default): the argmax or median of the mixture, exactly as on one
      policy's head;
    * ``vote``: per head, the value most members choose by the same selection, the mixture's
      where the most chosen values tie.

    Why combine: independently trained seeds fail in different scenarios, and where one member
    puts its mass on a bad value the others outvote it. Averaging logits instead would let one
    overconfident member decide alone. Why a vote beside the mixture: on an ordinal head whose
    members split between the two ends (pass left, pass right), the mixture's median is the
    value between them (keep the lane), which none of them chose; a vote picks a side most of
    them chose. The members keep their own observation normalisers."""

    def __init__(self, payload: Mapping[str, Any], path: str | os.PathLike = "<memory>"):
        require_keys(path, payload, ENSEMBLE_KEYS, "ensemble file", ENSEMBLE_FORMAT)
        if payload["version"] != FORMAT_VERSION:
            raise CheckpointError(path, f"format version {payload['version']!r}, this code reads {FORMAT_VERSION}")
        members = payload["members"]
        if not isinstance(members, (list, tuple)) or len(members) < 2:
            raise CheckpointError(path, "an ensemble needs a list of at least 2 member policies")
        self.members = [Policy(m, f"{path}[member {i}]") for i, m in enumerate(members)]
        first = self.members[0]
        for i, m in enumerate(self.members[1:], 1):
            if (m.obs_dim, m.nvec) != (first.obs_dim, first.nvec):
                raise CheckpointError(path, f"member {i} takes observations of size {m.obs_dim} and acts over "
                                            f"nvec={list(m.nvec)}; member 0: {first.obs_dim}, {list(first.nvec)}")
            differ = [k for k in ENSEMBLE_SHARED_META if m.meta.get(k) != first.meta.get(k)]
            if differ:
                raise CheckpointError(path, f"member {i} records another {', '.join(differ)} than member 0; "
                                            "the members of an ensemble must be trained alike")
        self.path = str(path)
        self.obs_dim, self.nvec = first.obs_dim, first.nvec
        self.config_hash = "+".join(m.config_hash for m in self.members)
        self.meta = dict(payload["meta"])
        for k in ENSEMBLE_SHARED_META:
            if k in first.meta:
                self.meta.setdefault(k, first.meta[k])
        self.selection = str(self.meta.get("action_selection", "argmax"))
        if self.selection not in DEPLOYED_SELECTIONS:
            raise CheckpointError(path, f"metadata action_selection {self.selection!r} is not one of "
                                        f"{DEPLOYED_SELECTIONS}")
        self.combine = str(self.meta.get("combine", "mixture"))
        if self.combine not in ENSEMBLE_COMBINES:
            raise CheckpointError(path, f"metadata combine {self.combine!r} is not one of {ENSEMBLE_COMBINES}")

    def act(self, obs: np.ndarray, deterministic: bool = True,
            rng: np.random.Generator | None = None) -> np.ndarray:
        """The mixture's argmax per head (``combine: vote``: the members' argmaxes voted), or a
        draw from the mixture."""
        if not deterministic:
            return super().act(obs, deterministic, rng)
        return self._decide(obs, lambda z: int(np.argmax(z)))

    def act_median(self, obs: np.ndarray) -> np.ndarray:
        """The mixture's median per head (``combine: vote``: the members' medians voted)."""
        return self._decide(obs, head_median)

    def logits(self, obs: np.ndarray) -> list[np.ndarray]:
        """Per head, the log of the mean of the members' probabilities (a mixture)."""
        return self._mixture([m.logits(obs) for m in self.members])

    def _decide(self, obs: np.ndarray, select) -> np.ndarray:
        """``select`` (one head's logits -> value) on the mixture, or voted over the members."""
        per_member = [m.logits(obs) for m in self.members]
        mixed = np.array([select(z) for z in self._mixture(per_member)], np.int64)
        if self.combine == "mixture":
            return mixed
        return _plurality(np.array([[select(z) for z in heads] for heads in per_member]), mixed)

    def _mixture(self, per_member: list[list[np.ndarray]]) -> list[np.ndarray]:
        log_k = math.log(len(per_member))
        out = []
        for h in range(len(self.nvec)):
            z = np.stack([heads[h] for heads in per_member]).astype(np.float64)
            z -= z.max(axis=1, keepdims=True)
            logp = z - np.log(np.exp(z).sum(axis=1, keepdims=True))     # each member's log-probabilities
            top = logp.max(axis=0)
            out.append(top + np.log(np.exp(logp - top).sum(axis=0)) - log_k)
        return out


def _plurality(votes: np.ndarray, tie: np.ndarray) -> np.ndarray:
    """Per column of ``votes`` (members x heads), the value most rows hold; ``tie``'s where the
    most held values tie."""
    out = np.array(tie, np.int64)
    for h in range(votes.shape[1]):
        values, counts = np.unique(votes[:, h], return_counts=True)
        if np.count_nonzero(counts == counts.max()) == 1:
            out[h] = values[np.argmax(counts)]
    return out


def head_median(logits: np.ndarray) -> int:
    """The median of one head's categorical over its ordered values: the smallest index whose
    cumulative probability reaches one half.

    Every head of the action space is ordinal (A1: waypoints by distance, A2: speeds in
    increasing order, A3: left / keep / right), so the median is a deterministic choice that
    follows the head's mass rather than its single largest value: 35 % on 0 m/s against 65 %
    spread over 2-8 m/s is a stop under argmax and a move under the median. It is also the value
    that minimises the expected distance to a draw, and ties the argmax when one value holds more
    than half the mass."""
    z = np.asarray(logits, np.float64)
    p = np.exp(z - z.max())
    c = np.cumsum(p / p.sum())
    return int(min(np.searchsorted(c, 0.5 - 1e-12), len(c) - 1))


ACTION_SELECTIONS = ("argmax", "median", "sample")


class MedianPolicy:
    """A policy run by each head's median (``head_median``): deterministic like the argmax, but
    a head split between stopping and several ways of moving moves. Same interface as ``Policy``
    for the planner and the evaluation (``act(obs)``)."""

    def __init__(self, policy: Policy):
        self.policy = policy
        self.obs_dim, self.nvec, self.path = policy.obs_dim, policy.nvec, policy.path
        self.meta = policy.meta

    def act(self, obs: np.ndarray, deterministic: bool = True) -> np.ndarray:
        return self.policy.act_median(obs)


def with_selection(policy: Policy, selection: str, seed: int = 0):
    """``policy`` acting by ``selection`` (one of ``ACTION_SELECTIONS``); ValueError otherwise."""
    if selection == "argmax":
        return policy
    if selection == "median":
        return MedianPolicy(policy)
    if selection == "sample":
        return SampledPolicy(policy, seed)
    raise ValueError(f"action selection must be one of {ACTION_SELECTIONS}, got {selection!r}")


class SampledPolicy:
    """A policy run as the stochastic policy PPO trained: every head's action drawn from its
    categorical distribution, with the generator re-seeded from ``(seed, episode)`` at each
    episode so that a run is reproducible and does not depend on the order episodes are played.

    Why it exists beside the argmax: the heads are independent, so the per-head argmax is the
    joint mode, but the mode of a head need not carry the head's decision. With five speeds, a
    0 m/s that holds 35 % of the mass wins the argmax although 65 % says "move", and a policy
    trained to wait and then go can stand forever under argmax where its own distribution goes."""

    def __init__(self, policy: Policy, seed: int = 0):
        self.policy = policy
        self.seed = int(seed)
        self.obs_dim, self.nvec, self.path = policy.obs_dim, policy.nvec, policy.path
        self.meta = policy.meta
        self.rng = np.random.default_rng([self.seed, 0])

    def begin_episode(self, episode: int) -> None:
        self.rng = np.random.default_rng([self.seed, int(episode)])

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.policy.act(obs, deterministic=False, rng=self.rng)
