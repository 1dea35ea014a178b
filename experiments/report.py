"""What the experiment scripts share: the machine line of a report, and writing a markdown report."""

from __future__ import annotations

import os
import platform
from typing import Any

import jax
import numpy as np


def machine() -> str:
    """The machine a figure was measured on, e.g. 'x86_64, 2 CPU cores, jax 0.10.2 on cpu (cpu)'."""
    return (f"{platform.machine()}, {os.cpu_count()} CPU cores, jax {jax.__version__} on {jax.default_backend()} "
            f"({jax.devices()[0].device_kind})")


def write(lines: list[str], path: str) -> None:
    """Prints a markdown report and writes it to `path` (creating its folder)."""
    table = "\n".join(lines)
    print(table)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(path, "w") as f:
        f.write(table + "\n")


def coverage_at(num_evaluations: np.ndarray, coverage: np.ndarray, evaluations: float) -> np.ndarray:
    """[S] each run's coverage once `evaluations` evaluations were spent, from per-generation
    num_evaluations [S, G] and coverage [S, G] (linear between generations)."""
    return np.array([np.interp(evaluations, e, c) for e, c in zip(num_evaluations, coverage, strict=True)])


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend, or None (with a message) when matplotlib is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed (pip install -e .[plot]): no figure written")
        return None
    return plt
