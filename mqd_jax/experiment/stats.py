"""Significance of a difference between two sets of runs, and bootstrap intervals (numpy only)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from mqd_jax.core.checks import is_int


def mann_whitney(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Two-sided Mann-Whitney U test of samples a [n] and b [m].

    Returns U (of `a`: the number of pairs where a's value is larger, ties
    counting one half) and the p-value from the normal approximation with the
    tie correction and a continuity correction (fine from about 8 runs a side;
    with fewer, read it as a rough guide).
    """
    a, b = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
    n, m = len(a), len(b)
    if n == 0 or m == 0:
        raise ValueError(f"mann_whitney needs two non-empty samples, got {n} and {m} values")
    both = np.concatenate([a, b])
    _, inverse, counts = np.unique(both, return_inverse=True, return_counts=True)
    # Mid-ranks: each distinct value's rank is the mean of the positions it spans.
    ranks = (np.cumsum(counts) - (counts - 1) / 2.0)[inverse]
    u = ranks[:n].sum() - n * (n + 1) / 2.0
    mean = n * m / 2.0
    ties = (counts ** 3 - counts).sum() / ((n + m) * (n + m - 1)) if n + m > 1 else 0.0
    var = n * m / 12.0 * ((n + m + 1) - ties)
    if var <= 0:
        return float(u), 1.0
    z = (abs(u - mean) - 0.5) / math.sqrt(var)
    return float(u), float(min(1.0, math.erfc(max(z, 0.0) / math.sqrt(2.0))))


def bootstrap_interval(statistic: Callable[..., float], groups: Sequence[np.ndarray], level: float = 0.9,
                       draws: int = 2000, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of statistic(*groups) at `level`.

    Each group [S_i, ...] (the runs of one side, e.g. seeds' curves) is
    resampled along its first axis with replacement, independently of the
    others, `draws` times. Returns the draws' lower and upper (1 - level) / 2
    quantiles, each one of the drawn values (so a statistic may be +inf, say
    "never reached", and an end reads inf). Deterministic for a given `seed`.
    """
    if not 0 < level < 1:
        raise ValueError(f"bootstrap_interval: level={level!r} is invalid: expected a float in (0, 1)")
    if not (is_int(draws) and draws >= 1):
        raise ValueError(f"bootstrap_interval: draws={draws!r} is invalid: expected an int >= 1")
    groups = [np.asarray(g) for g in groups]
    if not groups or any(len(g) == 0 for g in groups):
        raise ValueError(f"bootstrap_interval needs non-empty groups, got sizes {[len(g) for g in groups]}")
    rng = np.random.default_rng(seed)
    values = np.array([statistic(*(g[rng.integers(0, len(g), len(g))] for g in groups)) for _ in range(draws)],
                      np.float64)
    tail = (1 - level) / 2
    return float(np.quantile(values, tail, method="lower")), float(np.quantile(values, 1 - tail, method="higher"))
