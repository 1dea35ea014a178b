"""Significance of a difference between two sets of runs (numpy only)."""

from __future__ import annotations

import math

import numpy as np


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
