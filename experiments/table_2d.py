"""Coverage, quality and sample efficiency of M-QD, QD and RANDOM on the 2D tasks (paper settings).

    python experiments/table_2d.py [--seeds 5] [--generations 250] [--out results/table_2d.md]

Variants: `qd`, `mqd` (this library's default M-QD), `mqd-paper` (the paper's filter),
`mqd-paper-budget` (budgeted filtering, 4x pool), `random`. Each is compiled once and run for every seed in turn
(sequential runs are faster than vmapped ones on a CPU; see the README).
Writes a markdown table with mean +- std over seeds of the final coverage and
mean quality, the evaluations spent, the evaluations each M-QD variant needed
to reach QD's mean final coverage, QD's coverage after as many evaluations as
the variant spent in all, and the time per generation (compilation excluded)
with its ratio to QD's.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import jax
import numpy as np
import report

from mqd_jax import Config, run_mqd

VARIANTS: dict[str, dict[str, Any]] = {
    "qd": dict(algorithm="qd"),
    "mqd": dict(algorithm="mqd"),
    "mqd-paper": dict(algorithm="mqd-paper"),
    "mqd-paper-budget": dict(algorithm="mqd-paper", budgeted=True, pool_factor=4),
    "random": dict(algorithm="random"),
}


def _runs(cfg: Config, seeds: int) -> tuple[dict[str, np.ndarray], float]:
    """Per-generation metrics [seeds, G] of `seeds` runs, and ms per generation."""
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    compiled = run_mqd.lower(keys[0], cfg).compile()
    start = time.perf_counter()
    out = [jax.block_until_ready(compiled(k))[1] for k in keys]
    ms = (time.perf_counter() - start) / (seeds * cfg.max_generations) * 1e3
    return {k: np.stack([np.asarray(m[k]) for m in out]) for k in out[0]}, ms


def _evaluations_to_reach(m: dict[str, np.ndarray], coverage: float) -> list[int]:
    """Evaluations spent when each seed first reached `coverage` (seeds that never did are left out)."""
    return [int(e[np.argmax(c >= coverage)]) for e, c in zip(m["num_evaluations"], m["coverage"], strict=True)
            if (c >= coverage).any()]


def _pm(x: np.ndarray) -> str:
    return f"{np.mean(x):.3f} +- {np.std(x):.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--generations", type=int, default=250)
    parser.add_argument("--tasks", nargs="*", default=["obstacle2d", "object2d"])
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--out", default="results/table_2d.md")
    args = parser.parse_args()
    lines = [f"Paper 2D settings (Table II), {args.generations} generations, {args.seeds} seeds; "
             f"{report.machine()}.",
             "", "| task | variant | coverage | mean quality | evaluations | evaluations to QD's final coverage "
             "| QD's coverage at these evaluations | repertoire size | ms / generation | time vs QD |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for task in args.tasks:
        results = {}
        for name in args.variants:
            cfg = Config.paper_2d(task=task, max_generations=args.generations, **VARIANTS[name])
            results[name] = m, ms = _runs(cfg, args.seeds)
            dropped = int(m["dropped_full"].sum())
            if dropped:
                print(f"warning: {dropped} new niches dropped: raise Config.capacity above {cfg.capacity}")
            spent = m["num_evaluations"][:, -1]
            reach, qd_at = "", ""
            if "qd" in results:
                qd = results["qd"][0]
                target = qd["coverage"][:, -1].mean()
                hits = _evaluations_to_reach(m, target)
                reach = f"{np.mean(hits):.0f} ({len(hits)}/{args.seeds} seeds)" if hits else f"never (0/{args.seeds})"
                qd_at = _pm(report.coverage_at(qd["num_evaluations"], qd["coverage"], spent.mean()))
            ratio = f"{ms / results['qd'][1]:.2f}x" if "qd" in results else ""
            lines.append(f"| {task} | {name} | {_pm(m['coverage'][:, -1])} | {_pm(m['mean_quality'][:, -1])} "
                         f"| {spent.mean():.0f} | {reach} | {qd_at} | {m['repertoire_size'][:, -1].mean():.0f} "
                         f"| {ms:.2f} | {ratio} |")
            print(lines[-1], flush=True)
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
