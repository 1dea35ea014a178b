"""What the experiment scripts share beyond `mqd_jax.experiment.results` and `mqd_jax.experiment.plots`."""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import jax
import numpy as np

from mqd_jax.experiment.plots import pyplot
from mqd_jax.experiment.provenance import machine
from mqd_jax.experiment.tables import write_markdown as write

__all__ = ["coverage_at", "machine", "median_ms", "probe_arguments", "pyplot", "write"]


def coverage_at(num_evaluations: np.ndarray, coverage: np.ndarray, evaluations: float) -> np.ndarray:
    """[S] each run's coverage once `evaluations` evaluations were spent, from per-generation
    num_evaluations [S, G] and coverage [S, G] (linear between generations)."""
    return np.array([np.interp(evaluations, e, c) for e, c in zip(num_evaluations, coverage, strict=True)])


def median_ms(fn: Callable[[], object], repeats: int) -> float:
    """The median wall time in ms of `repeats` calls of `fn` (each waited for), after one untimed call."""
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e3


def probe_arguments(doc: str, tasks: list[str], seeds: int, out: str, choices: dict[str, tuple[str, ...]] | None = None,
                    **ints: int) -> argparse.Namespace:
    """The command line of a probe of "mqd" runs: --tasks, --generations (default 100), --seeds, one int option
    per `ints` (name: default), one option per `choices` (name: its values, the first the default) and --out; the
    description is the first line of `doc`."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=tasks)
    parser.add_argument("--generations", type=int, default=100)
    parser.add_argument("--seeds", type=int, default=seeds)
    for name, default in ints.items():
        parser.add_argument(f"--{name}", type=int, default=default)
    for name, values in (choices or {}).items():
        parser.add_argument(f"--{name}", choices=values, default=values[0])
    parser.add_argument("--out", default=out)
    return parser.parse_args()
