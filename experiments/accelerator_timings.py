"""The search's own timings on whatever JAX device this process has: one table, the same command everywhere.

    python experiments/accelerator_timings.py [--seeds 25] [--out results/accelerator_timings.md]

Rows (2D Obstacle and 2D Object, the paper's 2D settings, 250 generations):
ms per generation of QD and M-QD (one run; median of 3 after compiling), and
the wall time of a `--seeds` sweep of each preset (`run_batch`, as `mqd sweep`
runs it: first call with compilation, and a second call). The header names the
host and the JAX device. With `experiments/bench_physics.py` (robot physics
per backend and batch) and `experiments/profile_generation.py` (where a
generation's time goes) it makes the CPU/GPU comparison of docs/benchmarks.md;
the whole Table I is `time mqd sweep --out results/paper`.
"""

from __future__ import annotations

import argparse
import time

import jax
import report

from mqd_jax import Config, run_mqd
from mqd_jax.experiment.sweep import run_batch, seed_keys


def ms_per_generation(cfg: Config) -> float:
    """ms per generation of `run_mqd` on `cfg`: compiled by a first call, then the median of 3 runs."""
    key = jax.random.PRNGKey(0)
    return report.median_ms(lambda: run_mqd(key, cfg), 3) / cfg.max_generations


def _sweep_seconds(cfg: Config, seeds: int) -> tuple[float, float]:
    """(first call with compilation, second call) wall seconds of a sweep of `seeds` runs."""
    out = []
    for _ in range(2):
        start = time.perf_counter()
        jax.block_until_ready(run_batch(cfg, seed_keys(seeds))[0])
        out.append(time.perf_counter() - start)
    return out[0], out[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=25)
    parser.add_argument("--out", default="results/accelerator_timings.md")
    args = parser.parse_args()
    device = f"{report.machine()}; JAX device: {jax.devices()[0].device_kind} x {jax.device_count()}"
    lines = [f"Paper 2D settings, 250 generations; {device}.", "",
             "| task | algorithm | ms / generation (one run) | sweep of " f"{args.seeds} seeds, s (with compile) | "
             "same, second call, s |", "|---|---|---|---|---|"]
    for task in ("obstacle2d", "object2d"):
        for algorithm in ("qd", "mqd", "random"):
            cfg = Config.paper_2d(task=task, algorithm=algorithm)
            ms = ms_per_generation(cfg) if algorithm != "random" else float("nan")
            first, second = _sweep_seconds(cfg, args.seeds)
            lines.append(f"| {task} | {algorithm} | {ms:.2f} | {first:.1f} | {second:.1f} |")
            print(lines[-1], flush=True)
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
