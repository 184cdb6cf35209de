"""Figures and tables of the curriculum, in the form of the paper's Figs. 5-6 and Table I.

Input is a *history*: a list of ``scheduler.log_dict()`` snapshots taken during training
(each has ``episodes``). Keeping the input this plain lets the training loop, the ROS node
and the synthetic learner all feed the same functions, e.g. from a JSON-lines log.
"""
from __future__ import annotations

import pathlib
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (backend must be chosen first)
import numpy as np  # noqa: E402

TASK_NAMES = ("left", "straight", "right")


def _n_clusters(rec: Mapping[str, float]) -> int:
    n = 0
    while f"cluster_prob_{n}" in rec:
        n += 1
    if n == 0:
        raise ValueError("history records have no 'cluster_prob_0': not scheduler.log_dict() snapshots")
    return n


def _check(history: Sequence[Mapping[str, float]]) -> None:
    if len(history) == 0:
        raise ValueError("history is empty: record at least one log_dict() snapshot")
    for k, rec in enumerate(history):
        if "episodes" not in rec:
            raise ValueError(f"history[{k}] has no 'episodes' key")


def _series(history, key):
    missing = [k for k, rec in enumerate(history) if key not in rec]
    if missing:
        raise ValueError(f"history[{missing[0]}] has no key '{key}' (is this a bandit scheduler's log?)")
    return np.array([rec[key] for rec in history], dtype=float)


def _save(fig, path) -> pathlib.Path:
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_cluster_weights(history, path, title: str = "Cluster weights (Fig. 5 style)") -> pathlib.Path:
    """Target-BiMAB cluster weights (solid, updated every episode) and the sampling copy
    (dashed steps, changes only at syncs), one colour per N_sv."""
    _check(history)
    x = _series(history, "episodes")
    fig, ax = plt.subplots(figsize=(7, 4))
    for i in range(_n_clusters(history[0])):
        line, = ax.plot(x, _series(history, f"target_cluster_weight_{i}"), label=f"$N_{{sv}}={i}$")
        ax.step(x, _series(history, f"cluster_weight_{i}"), where="post", ls="--", lw=0.8, color=line.get_color())
    ax.set_xlabel("episode")
    ax.set_ylabel("weight (re-centred, level mean = initial weight)")
    ax.set_title(title + "\nsolid: target BiMAB, dashed: sampling BiMAB")
    ax.legend(loc="best")
    ax.grid(alpha=0.3)
    return _save(fig, path)


def plot_arm_weights(history, path, title: str = "Arm weights per cluster (Fig. 6 style)") -> pathlib.Path:
    """One panel per cluster with the three task-arm weights of the target BiMAB."""
    _check(history)
    x = _series(history, "episodes")
    n = _n_clusters(history[0])
    cols = 2
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(10, 3.2 * rows), sharex=True, squeeze=False)
    for i in range(n):
        ax = axes[i // cols][i % cols]
        for j, task in enumerate(TASK_NAMES):
            line, = ax.plot(x, _series(history, f"target_arm_weight_{i}_{j}"), label=task)
            ax.step(x, _series(history, f"arm_weight_{i}_{j}"), where="post", ls="--", lw=0.8, color=line.get_color())
        ax.set_title(f"$N_{{sv}}={i}$")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("episode")
    fig.suptitle(title + " — solid: target, dashed: sampling")
    fig.tight_layout()
    return _save(fig, path)


def plot_cluster_probabilities(history, path, title: str = "Cluster sampling probabilities") -> pathlib.Path:
    """p_cluster of the sampling law over training: works for every scheduler, bandit or not."""
    _check(history)
    x = _series(history, "episodes")
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for i in range(_n_clusters(history[0])):
        ax.step(x, _series(history, f"cluster_prob_{i}"), where="post", label=f"$N_{{sv}}={i}$")
    ax.set_xlabel("episode")
    ax.set_ylabel("p(cluster)")
    ax.set_ylim(0, 1)
    ax.set_title(title)
    ax.legend(loc="best")
    ax.grid(alpha=0.3)
    return _save(fig, path)


def plot_curves(curves: Mapping[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]], path,
                ylabel: str, title: str) -> pathlib.Path:
    """Several named curves (x, mean, spread-or-None) on one axis, spread drawn as a band."""
    if not curves:
        raise ValueError("no curves to plot")
    fig, ax = plt.subplots(figsize=(7, 4))
    styles = ("-", "--", "-.", ":", (0, (8, 2, 1, 2)))   # curves that coincide stay distinguishable
    for k, (name, (x, y, spread)) in enumerate(curves.items()):
        line, = ax.plot(x, y, label=name, ls=styles[k % len(styles)], lw=1.8)
        if spread is not None:
            ax.fill_between(x, y - spread, y + spread, color=line.get_color(), alpha=0.2)
    ax.set_xlabel("episode")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(loc="best")
    ax.grid(alpha=0.3)
    return _save(fig, path)


def counts_table_markdown(log: Mapping[str, float]) -> str:
    """Table I style: sampled times per cluster and per (cluster, task) arm, as markdown."""
    n = _n_clusters(log)
    head = "| N_sv | sampled | " + " | ".join(f"{t} (j={j})" for j, t in enumerate(TASK_NAMES)) + " |"
    lines = [head, "|---:|---:|" + "---:|" * len(TASK_NAMES)]
    col_tot = [0] * len(TASK_NAMES)
    for i in range(n):
        arms = [int(log[f"count_{i}_{j}"]) for j in range(len(TASK_NAMES))]
        col_tot = [a + b for a, b in zip(col_tot, arms)]
        lines.append(f"| {i} | {int(log[f'count_{i}'])} | " + " | ".join(str(a) for a in arms) + " |")
    lines.append(f"| all | {sum(col_tot)} | " + " | ".join(str(a) for a in col_tot) + " |")
    return "\n".join(lines)
