"""What the experiment scripts share beyond `mqd_jax.results` and `mqd_jax.plots`."""

from __future__ import annotations

import numpy as np

from mqd_jax.plots import pyplot
from mqd_jax.provenance import machine
from mqd_jax.results import write_markdown as write

__all__ = ["coverage_at", "machine", "pyplot", "write"]


def coverage_at(num_evaluations: np.ndarray, coverage: np.ndarray, evaluations: float) -> np.ndarray:
    """[S] each run's coverage once `evaluations` evaluations were spent, from per-generation
    num_evaluations [S, G] and coverage [S, G] (linear between generations)."""
    return np.array([np.interp(evaluations, e, c) for e, c in zip(num_evaluations, coverage, strict=True)])
