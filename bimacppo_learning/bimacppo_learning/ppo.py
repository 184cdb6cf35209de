"""PPO for the MultiDiscrete([5, 5, 3]) high-level action of BiM-ACPPO (paper §III-C, §IV-A).

One actor MLP emits sum(nvec) logits, split into one categorical head per sub-action
(waypoint, speed, lane change); the sub-actions are sampled independently given the
observation, so the joint log-probability is the sum of the heads' log-probabilities and
the joint entropy the sum of their entropies.  The critic is a separate MLP with its own
Adam optimiser (the paper gives the two networks different learning rates).

The paper's "temporary policy network" (Algorithm 2) is PPO's old policy pi_theta_old:
we keep it implicitly as the log-probabilities recorded when the rollout was collected,
which is what the ratio in eq. (30) needs.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Mapping, Sequence

import numpy as np
import torch
from torch import nn

from .ppo_config import PPOConfig

_ACT = {"tanh": nn.Tanh, "relu": nn.ReLU}


def build_mlp(in_dim: int, hidden: Sequence[int], out_dim: int, activation: str,
              gain_hidden: float, gain_out: float) -> nn.Sequential:
    """Orthogonal init (PPO practice): stable early updates; tiny output gain = near-uniform policy."""
    layers: list[nn.Module] = []
    last = in_dim
    for h in hidden:
        lin = nn.Linear(last, h)
        nn.init.orthogonal_(lin.weight, gain_hidden)
        nn.init.zeros_(lin.bias)
        layers += [lin, _ACT[activation]()]
        last = h
    out = nn.Linear(last, out_dim)
    nn.init.orthogonal_(out.weight, gain_out)
    nn.init.zeros_(out.bias)
    layers.append(out)
    return nn.Sequential(*layers)


class MultiCategorical:
    """Independent categorical heads over one logits vector split by ``nvec``."""

    def __init__(self, logits: torch.Tensor, nvec: Sequence[int]):
        if logits.shape[-1] != sum(nvec):
            raise ValueError(f"logits last dim {logits.shape[-1]} != sum(nvec) {sum(nvec)}")
        self.nvec = tuple(int(n) for n in nvec)
        self.log_probs = [torch.log_softmax(part, dim=-1)
                          for part in torch.split(logits, self.nvec, dim=-1)]

    def log_prob(self, actions: torch.Tensor) -> torch.Tensor:
        """Joint log-probability: sum over heads.  actions: (..., n_heads) integer."""
        if actions.shape[-1] != len(self.nvec):
            raise ValueError(f"actions last dim {actions.shape[-1]} != number of heads {len(self.nvec)}")
        a = actions.long()
        return sum(lp.gather(-1, a[..., k:k + 1]).squeeze(-1) for k, lp in enumerate(self.log_probs))

    def head_log_probs(self, actions: torch.Tensor) -> torch.Tensor:
        a = actions.long()
        return torch.stack([lp.gather(-1, a[..., k:k + 1]).squeeze(-1)
                            for k, lp in enumerate(self.log_probs)], dim=-1)

    def entropy(self) -> torch.Tensor:
        return sum(-(lp.exp() * lp).sum(-1) for lp in self.log_probs)

    def mode(self) -> torch.Tensor:
        return torch.stack([lp.argmax(-1) for lp in self.log_probs], dim=-1)

    def sample(self, generator: torch.Generator | None = None) -> torch.Tensor:
        cols = []
        for lp in self.log_probs:
            flat = lp.exp().reshape(-1, lp.shape[-1])
            cols.append(torch.multinomial(flat, 1, generator=generator).reshape(lp.shape[:-1]))
        return torch.stack(cols, dim=-1)


class RunningMeanStd:
    """Running mean/variance of observations (Chan et al. parallel update), float64 for stability."""

    def __init__(self, dim: int, eps: float, clip: float):
        self.mean = np.zeros(dim, np.float64)
        self.var = np.ones(dim, np.float64)
        self.count = 0.0
        self.eps = float(eps)
        self.clip = float(clip)

    def update(self, x: np.ndarray) -> None:
        x = np.asarray(x, np.float64).reshape(-1, self.mean.shape[0])
        n = x.shape[0]
        if n == 0:
            return
        b_mean, b_var = x.mean(0), x.var(0)
        tot = self.count + n
        delta = b_mean - self.mean
        self.mean = self.mean + delta * n / tot
        self.var = (self.var * self.count + b_var * n + delta ** 2 * self.count * n / tot) / tot
        self.count = tot

    def normalize(self, x: np.ndarray) -> np.ndarray:
        if self.count == 0:
            return np.clip(np.asarray(x, np.float32), -self.clip, self.clip)
        z = (np.asarray(x, np.float64) - self.mean) / np.sqrt(self.var + self.eps)
        return np.clip(z, -self.clip, self.clip).astype(np.float32)

    def state_dict(self) -> dict:
        return {"mean": torch.from_numpy(self.mean.copy()), "var": torch.from_numpy(self.var.copy()),
                "count": float(self.count), "eps": self.eps, "clip": self.clip}

    def load_state_dict(self, d: Mapping) -> None:
        mean = np.asarray(d["mean"], np.float64)
        var = np.asarray(d["var"], np.float64)
        if mean.shape != self.mean.shape or var.shape != self.var.shape:
            raise ValueError(f"obs normaliser shape {tuple(mean.shape)} != expected {self.mean.shape}")
        self.mean, self.var, self.count = mean.copy(), var.copy(), float(d["count"])
        self.eps, self.clip = float(d["eps"]), float(d["clip"])


def clipped_surrogate(new_logp: torch.Tensor, old_logp: torch.Tensor, adv: torch.Tensor,
                      clip_eps: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Eq. (30) as a loss to minimise: -E[min(rho A, clip(rho, 1-eps, 1+eps) A)].

    Returns (loss, clip_fraction, approx_kl); approx_kl is the low-variance k3 estimator
    E[(rho - 1) - log rho] of KL(old || new).
    """
    log_ratio = new_logp - old_logp
    ratio = log_ratio.exp()
    unclipped = ratio * adv
    clipped = ratio.clamp(1.0 - clip_eps, 1.0 + clip_eps) * adv
    loss = -torch.min(unclipped, clipped).mean()
    with torch.no_grad():
        clip_frac = ((ratio - 1.0).abs() > clip_eps).float().mean()
        approx_kl = ((ratio - 1.0) - log_ratio).mean()
    return loss, clip_frac, approx_kl


# Adam as one compiled kernel per parameter group (torch's fused CPU implementation): the same
# update rule as the per-tensor loop, in a fraction of its operator calls; a PPO update makes 160
# optimiser steps on networks of a few tensors each, where those calls, not the arithmetic, cost.
FUSED_ADAM = {"fused": True, "foreach": None}


def adam(params, lr: float, eps: float) -> torch.optim.Adam:
    return torch.optim.Adam(params, lr=lr, eps=eps, **FUSED_ADAM)


# PPO settings that define a trained agent (its networks, and whether its inputs are normalised):
# a fine-tune can change every other setting, not these.
ARCHITECTURE_KEYS = ("hidden_sizes", "activation", "obs_norm")


class PPO:
    """Actor, critic, their optimisers, the observation normaliser and the sampling RNG."""

    def __init__(self, obs_dim: int, nvec: Sequence[int], config: PPOConfig | None = None,
                 seed: int = 0):
        if int(obs_dim) < 1:
            raise ValueError(f"obs_dim must be >= 1, got {obs_dim}")
        nvec = tuple(int(n) for n in nvec)
        if len(nvec) == 0 or min(nvec) < 1:
            raise ValueError(f"nvec must be a non-empty list of positive sizes, got {nvec}")
        self.cfg = config or PPOConfig()
        self.obs_dim = int(obs_dim)
        self.nvec = nvec
        c = self.cfg
        with torch.random.fork_rng(devices=[]):  # seeded init without touching the caller's RNG
            torch.manual_seed(int(seed))
            self.actor = build_mlp(self.obs_dim, c.hidden_sizes, sum(nvec), c.activation,
                                   c.init_gain_hidden, c.init_gain_policy)
            self.critic = build_mlp(self.obs_dim, c.hidden_sizes, 1, c.activation,
                                    c.init_gain_hidden, c.init_gain_value)
        self.actor_opt = adam(self.actor.parameters(), c.actor_lr, c.adam_eps)
        self.critic_opt = adam(self.critic.parameters(), c.critic_lr, c.adam_eps)
        self.entropy_coef = float(c.entropy_coef)   # moved by set_progress under entropy_schedule
        self.obs_rms = RunningMeanStd(self.obs_dim, c.obs_norm_eps, c.obs_clip)
        # Own generator: action sampling and minibatch shuffles stay reproducible whatever else
        # (env code, other libraries) draws from torch's global RNG.
        self.gen = torch.Generator().manual_seed(int(seed))

    # ----------------------------------------------------------------- inference
    def normalize_obs(self, obs: np.ndarray, update: bool = False) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        if obs.shape[-1] != self.obs_dim:
            raise ValueError(f"observation last dim {obs.shape[-1]} != obs_dim {self.obs_dim}")
        if not np.all(np.isfinite(obs)):
            raise ValueError("observation contains NaN or inf")
        if not self.cfg.obs_norm:
            return obs
        if update:
            self.obs_rms.update(obs)
        return self.obs_rms.normalize(obs)

    def dist(self, obs_n: torch.Tensor) -> MultiCategorical:
        return MultiCategorical(self.actor(obs_n), self.nvec)

    @torch.no_grad()
    def act(self, obs_n: np.ndarray, deterministic: bool = False
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Normalised obs (N, D) -> actions (N, heads) int64, joint log-probs (N,), values (N,)."""
        x = torch.as_tensor(obs_n, dtype=torch.float32)
        d = self.dist(x)
        a = d.mode() if deterministic else d.sample(self.gen)
        return (a.numpy().astype(np.int64), d.log_prob(a).numpy(),
                self.critic(x).squeeze(-1).numpy())

    @torch.no_grad()
    def value(self, obs_n: np.ndarray) -> np.ndarray:
        x = torch.as_tensor(obs_n, dtype=torch.float32)
        return self.critic(x).squeeze(-1).numpy()

    # -------------------------------------------------------------------- update
    def update(self, obs: np.ndarray, actions: np.ndarray, old_logp: np.ndarray,
               advantages: np.ndarray, returns: np.ndarray, fit_actor: bool = True,
               critic_thread: bool = False) -> dict[str, float]:
        """`epochs` passes of shuffled minibatches over one flattened rollout.

        Actor loss = clipped surrogate - entropy coefficient * entropy (``self.entropy_coef``, the
        config's value moved by its schedule in ``set_progress``); critic loss = MSE to the GAE
        returns; each network has its own optimiser and grad-norm clip. ``fit_actor`` False fits
        the critic alone (``critic_warmup_updates``): the actor's weights and optimiser moments
        stay as they are, and its losses are still reported.

        The two networks share no tensor and no loss term, so each epoch fits the actor on every
        minibatch of the epoch's permutation and then the critic on the same minibatches (the
        result equals any interleaving of the two). ``critic_thread`` True runs the critic's passes
        on a second thread while this one fits the actor: torch releases the interpreter lock
        inside its operators, so the two fits overlap on two cores, and the result is the serial
        one bit for bit (each network's operators run in the same order on one thread either way).
        The epochs stay in step (``target_kl`` reads the actor's KL after each)."""
        c = self.cfg
        n = obs.shape[0]
        if not (actions.shape[0] == old_logp.shape[0] == advantages.shape[0] == returns.shape[0] == n):
            raise ValueError("rollout arrays have different lengths")
        if n == 0:
            raise ValueError("empty rollout")
        O = torch.as_tensor(obs, dtype=torch.float32)
        A = torch.as_tensor(actions, dtype=torch.long)
        LP = torch.as_tensor(old_logp, dtype=torch.float32)
        ADV = torch.as_tensor(advantages, dtype=torch.float32)
        RET = torch.as_tensor(returns, dtype=torch.float32)
        mb = min(c.minibatch_size, n)
        sums = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0, "approx_kl": 0.0,
                "clip_fraction": 0.0, "actor_grad_norm": 0.0, "critic_grad_norm": 0.0}
        steps = 0
        epochs_run = 0
        stop = False
        pool = ThreadPoolExecutor(1, thread_name_prefix="ppo-critic") if critic_thread else None
        try:
            for _ in range(c.epochs):
                perm = torch.randperm(n, generator=self.gen)
                # a 1-sample tail would give a meaningless normalised advantage
                batches = [perm[s:s + mb] for s in range(0, n, mb) if min(mb, n - s) >= 2 or n < 2]
                job = pool.submit(self._fit_critic, O, RET, batches) if pool is not None else None
                actor = self._fit_actor(O, A, LP, ADV, batches, fit_actor)
                critic = job.result() if job is not None else self._fit_critic(O, RET, batches)
                for key in ("value_loss", "critic_grad_norm"):
                    sums[key] += critic[key]
                for key in ("policy_loss", "entropy", "approx_kl", "clip_fraction", "actor_grad_norm"):
                    sums[key] += actor[key]
                steps += len(batches)
                epochs_run += 1
                if c.target_kl is not None and batches and actor["approx_kl"] / len(batches) > c.target_kl:
                    stop = True
                    break
        finally:
            if pool is not None:
                pool.shutdown(wait=True)
        stats = {k: v / max(steps, 1) for k, v in sums.items()}
        with torch.no_grad():
            v_pred = self.critic(O).squeeze(-1)
            var_ret = RET.var() if n > 1 else torch.tensor(0.0)
            stats["explained_variance"] = (float(1.0 - (RET - v_pred).var() / var_ret)
                                           if n > 1 and float(var_ret) > 0 else float("nan"))
        stats["epochs"] = float(epochs_run)
        stats["actor_fitted"] = float(fit_actor)
        stats["early_stop"] = float(stop)
        stats["minibatch_steps"] = float(steps)
        return stats

    def _fit_actor(self, O, A, LP, ADV, batches, fit: bool) -> dict[str, float]:
        """One epoch of the actor over ``batches`` (index tensors); the sums of its statistics.
        ``fit`` False only evaluates (the critic warm-up)."""
        c = self.cfg
        out = {"policy_loss": 0.0, "entropy": 0.0, "approx_kl": 0.0, "clip_fraction": 0.0, "actor_grad_norm": 0.0}
        for idx in batches:
            adv = ADV[idx]
            if c.normalize_advantages and adv.numel() > 1:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            with torch.set_grad_enabled(fit):
                d = self.dist(O[idx])
                new_lp = d.log_prob(A[idx])
                pl, cf, kl = clipped_surrogate(new_lp, LP[idx], adv, c.clip_eps)
                ent = d.entropy().mean()
            if fit:
                actor_loss = pl - self.entropy_coef * ent
                self.actor_opt.zero_grad(set_to_none=True)
                actor_loss.backward()
                agn = float(nn.utils.clip_grad_norm_(self.actor.parameters(), c.max_grad_norm))
                self.actor_opt.step()
            else:
                agn = 0.0
            for key, val in (("policy_loss", pl), ("entropy", ent), ("approx_kl", kl), ("clip_fraction", cf)):
                out[key] += float(val.detach())
            out["actor_grad_norm"] += agn
        return out

    def _fit_critic(self, O, RET, batches) -> dict[str, float]:
        """One epoch of the critic over ``batches``; the sums of its statistics. Runs on any thread:
        it touches only the critic, its optimiser and read-only inputs."""
        c = self.cfg
        out = {"value_loss": 0.0, "critic_grad_norm": 0.0}
        for idx in batches:
            v = self.critic(O[idx]).squeeze(-1)
            vl = 0.5 * (v - RET[idx]).pow(2).mean()
            self.critic_opt.zero_grad(set_to_none=True)
            vl.backward()
            out["critic_grad_norm"] += float(nn.utils.clip_grad_norm_(self.critic.parameters(), c.max_grad_norm))
            self.critic_opt.step()
            out["value_loss"] += float(vl.detach())
        return out

    def adopt_config(self, config: PPOConfig) -> None:
        """Train on under ``config`` from now on (a fine-tune's own PPO settings).

        The networks, their optimiser moments and the normaliser's statistics are kept; the
        optimisers take the new rates and epsilon, the normaliser the new clip and variance floor.
        Settings that shape what the agent already is cannot change: raises ValueError naming them."""
        fixed = [k for k in ARCHITECTURE_KEYS if getattr(self.cfg, k) != getattr(config, k)]
        if fixed:
            raise ValueError("the PPO settings " + ", ".join(
                f"{k} ({getattr(self.cfg, k)!r} -> {getattr(config, k)!r})" for k in fixed)
                + " define the trained networks and cannot change in a fine-tune")
        self.cfg = config
        for opt in (self.actor_opt, self.critic_opt):
            for g in opt.param_groups:
                g["eps"] = config.adam_eps
        self.set_progress(0.0)
        self.obs_rms.eps = float(config.obs_norm_eps)
        self.obs_rms.clip = float(config.obs_clip)

    def set_progress(self, progress: float) -> None:
        """Move the scheduled settings (learning rates, entropy bonus) to where the config's
        schedules put them after ``progress`` (0..1) of the run's budget."""
        self.set_lr_fraction(self.cfg.lr_fraction(progress))
        self.entropy_coef = float(self.cfg.entropy_coef_at(progress))

    def set_lr_fraction(self, fraction: float) -> None:
        """Set both optimisers' rates to ``fraction`` x the configured actor_lr / critic_lr."""
        f = float(fraction)
        if not (0.0 <= f <= 1.0):
            raise ValueError(f"learning-rate fraction must be in [0, 1], got {fraction!r}")
        for opt, base in ((self.actor_opt, self.cfg.actor_lr), (self.critic_opt, self.cfg.critic_lr)):
            for g in opt.param_groups:
                g["lr"] = base * f

    # --------------------------------------------------------------- persistence
    def state_dict(self) -> dict:
        return {
            "obs_dim": self.obs_dim,
            "nvec": list(self.nvec),
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "obs_rms": self.obs_rms.state_dict(),
            "gen": self.gen.get_state(),
        }

    def load_state_dict(self, d: Mapping) -> None:
        """Shape-checked load; raises ValueError naming the first mismatching tensor."""
        if int(d["obs_dim"]) != self.obs_dim or tuple(d["nvec"]) != self.nvec:
            raise ValueError(f"agent built for obs_dim={self.obs_dim}, nvec={list(self.nvec)} but state has "
                             f"obs_dim={d['obs_dim']}, nvec={list(d['nvec'])}")
        for name, net in (("actor", self.actor), ("critic", self.critic)):
            check_state_shapes(name, net.state_dict(), d[name])
        self.actor.load_state_dict(d["actor"])
        self.critic.load_state_dict(d["critic"])
        for opt, key in ((self.actor_opt, "actor_opt"), (self.critic_opt, "critic_opt")):
            opt.load_state_dict(d[key])
            for g in opt.param_groups:      # a checkpoint saved by another Adam implementation
                g.update(FUSED_ADAM)
        self.obs_rms.load_state_dict(d["obs_rms"])
        self.gen.set_state(d["gen"])


def widen_inputs(agent: PPO, columns: Sequence[int]) -> PPO:
    """A copy of ``agent`` whose input j is the old input ``columns[j]`` (-1: a new input).

    New inputs get zero weights in the actor's and the critic's first layer and a normaliser
    entry of mean 0, variance 1, so the copy's actions and values equal the original's whatever
    the new inputs read: a fine-tune that adds observation features starts from the checkpoint's
    behaviour and learns what the new features are worth. The optimisers start afresh (their
    moments were for the old first layer); the sampling generator is carried over."""
    old_cols = [int(c) for c in columns]
    if any(c < -1 or c >= agent.obs_dim for c in old_cols):
        raise ValueError(f"columns must be -1 or an input of the agent (0..{agent.obs_dim - 1}), got {old_cols}")
    kept = [c for c in old_cols if c >= 0]
    if sorted(kept) != list(range(agent.obs_dim)):
        raise ValueError(f"columns must keep every one of the agent's {agent.obs_dim} inputs once, got {old_cols}")
    new = PPO(len(old_cols), agent.nvec, agent.cfg)
    src = torch.tensor([max(c, 0) for c in old_cols])
    fresh = torch.tensor([c < 0 for c in old_cols])
    with torch.no_grad():
        for old_net, new_net in ((agent.actor, new.actor), (agent.critic, new.critic)):
            state = {k: v.clone() for k, v in old_net.state_dict().items()}
            first = next(k for k in state if k.endswith("weight"))
            w = state[first][:, src].clone()
            w[:, fresh] = 0.0
            state[first] = w
            new_net.load_state_dict(state)
    rms = agent.obs_rms
    idx = np.array([max(c, 0) for c in old_cols])
    new.obs_rms.mean = np.where([c < 0 for c in old_cols], 0.0, rms.mean[idx])
    new.obs_rms.var = np.where([c < 0 for c in old_cols], 1.0, rms.var[idx])
    new.obs_rms.count = rms.count
    new.gen.set_state(agent.gen.get_state())
    return new


def set_head_prior(agent: PPO, head: int, probs: Sequence[float]) -> None:
    """Make action head ``head`` of ``agent``'s actor choose with probabilities ``probs`` whatever
    the observation, in place: its rows of the actor's output layer get zero weights and the
    biases log(probs). The other heads and the critic are untouched.

    Why: a fine-tune can hand a head a job its source never needed. The intersection policy's
    lane-change head (A3) is near uniform, and under ``action.lane_change_from: chosen`` every
    sampled left or right moves the car a whole lane, so at uniform odds the fine-tune's rollouts
    change lanes at every other decision. A prior that keeps the lane in most decisions leaves
    lane changes rare enough to be tried one at a time, and the fine-tune learns when to make
    them from there."""
    nvec = agent.nvec
    if not 0 <= int(head) < len(nvec):
        raise ValueError(f"head must be in 0..{len(nvec) - 1}, got {head}")
    p = np.asarray(probs, dtype=np.float64)
    if p.shape != (nvec[head],):
        raise ValueError(f"head {head} has {nvec[head]} actions, got {len(p)} probabilities")
    if not np.all(np.isfinite(p)) or np.any(p <= 0.0) or abs(p.sum() - 1.0) > 1e-9:
        raise ValueError(f"probabilities must be positive and sum to 1, got {p.tolist()}")
    out = agent.actor[-1]
    start = int(sum(nvec[:head]))
    rows = slice(start, start + int(nvec[head]))
    with torch.no_grad():
        out.weight[rows] = 0.0
        out.bias[rows] = torch.as_tensor(np.log(p), dtype=out.bias.dtype)
        # the optimiser's moments for these rows belonged to the old head: without this the
        # first updates would keep moving it along its source's gradients
        for param in (out.weight, out.bias):
            for moment in agent.actor_opt.state.get(param, {}).values():
                if torch.is_tensor(moment) and moment.shape == param.shape:
                    moment[rows] = 0.0


def check_state_shapes(name: str, expected: Mapping[str, torch.Tensor], got: Mapping) -> None:
    missing = sorted(set(expected) - set(got))
    extra = sorted(set(got) - set(expected))
    if missing or extra:
        raise ValueError(f"{name}: missing tensors {missing}, unexpected tensors {extra}")
    for k, t in expected.items():
        g = got[k]
        if not isinstance(g, torch.Tensor):
            raise ValueError(f"{name}.{k}: expected a tensor, got {type(g).__name__}")
        if tuple(g.shape) != tuple(t.shape):
            raise ValueError(f"{name}.{k}: shape {tuple(g.shape)} != expected {tuple(t.shape)}")
