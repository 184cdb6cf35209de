"""Statistics over seeds and episodes (pure functions: tested on synthetic data)."""
from __future__ import annotations

from typing import Mapping

import numpy as np


def aggregate_cells(tables: list[Mapping]) -> dict[tuple[int, int], dict]:
    """Per cell, mean and sample standard deviation (ddof=1; NaN for one seed) of S/C/TO
    across the given evaluation tables; a cell counts only the tables that have it."""
    keys = sorted({k for t in tables for k in t})
    out = {}
    for key in keys:
        a = np.array([t[key][:3] for t in tables if key in t], float)
        std = a.std(axis=0, ddof=1) if len(a) > 1 else np.full(3, np.nan)
        out[key] = {"n": len(a), "mean": a.mean(axis=0), "std": std}
    return out


def rolling_rate(recs: list[dict], window: int) -> tuple[np.ndarray, np.ndarray]:
    """(episode, success rate over the last ``window`` episodes), only where a full window exists."""
    from ..report import rolling_success

    x, y = rolling_success(recs, window)
    keep = x >= window
    return x[keep], y[keep]


def episodes_to_fraction(recs: list[dict], window: int, fraction: float) -> tuple[int | None, float]:
    """(first episode whose rolling success reaches ``fraction`` x the final one, final rate).
    Final = the rolling rate at the last episode. None when the run has no full window or its
    final rate is 0 (nothing to reach)."""
    x, y = rolling_rate(recs, window)
    if not len(x):
        return None, float("nan")
    final = float(y[-1])
    if final <= 0.0:
        return None, final
    hit = np.nonzero(y >= fraction * final - 1e-12)[0]
    return int(x[hit[0]]), final


def mean_std_curve(histories: list[list[dict]], window: int):
    """Rolling success of several seeds on their common episode range: (x, mean, std)."""
    curves = [rolling_rate(h, window) for h in histories]
    curves = [c for c in curves if len(c[0])]
    if not curves:
        return None
    hi = min(int(c[0][-1]) for c in curves)
    x = np.arange(window, hi + 1, dtype=float)
    ys = np.array([np.interp(x, cx, cy) for cx, cy in curves])
    return x, ys.mean(axis=0), ys.std(axis=0, ddof=1) if len(ys) > 1 else None


def mean_counts(logs: list[Mapping]) -> dict[str, float]:
    """Table I over seeds: mean of each count_i / count_i_j of the schedulers' final logs."""
    keys = sorted({k for lg in logs for k in lg if k.startswith("count_")})
    return {k: float(np.mean([lg.get(k, 0.0) for lg in logs])) for k in keys}
