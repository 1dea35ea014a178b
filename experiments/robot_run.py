"""QD and M-QD on a KUKA task with the paper's robot settings, and a picture of the repertoire on the table.

    python experiments/robot_run.py [--task push_cube] [--generations 100] [--seed 0] [--out results/robot]

Table II's robotic column (100 generations, population 100, 64 hidden
neurons). Prints and writes (robot_<task>.md) final coverage, mean quality,
evaluations and wall time (compilation separately) per algorithm, and draws
robot_<task>.png: the table from above (its layout: shelves, the object's
start, the via-points' reach) with each final repertoire's behaviors.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import numpy as np
import report

from mqd_jax import Config, run_mqd
from mqd_jax.core import registry
from mqd_jax.experiment import plots


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="push_cube")
    parser.add_argument("--generations", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="results/robot")
    args = parser.parse_args()
    key = jax.random.PRNGKey(args.seed)
    lines = [f"{args.task}, Table II robot settings, {args.generations} generations, seed {args.seed}; "
             f"{report.machine()}, C MuJoCo backend.", "",
             "| algorithm | coverage | mean quality | skills | evaluations | compile s | run s |",
             "|---|---|---|---|---|---|---|"]
    behaviors = {}
    for alg in ("qd", "mqd"):
        cfg = Config.paper_robot(task=args.task, algorithm=alg, max_generations=args.generations)
        start = time.perf_counter()
        compiled = run_mqd.lower(key, cfg).compile()
        compile_s = time.perf_counter() - start
        start = time.perf_counter()
        state, m = jax.block_until_ready(compiled(key))
        run_s = time.perf_counter() - start
        n = int(state.repertoire.count)
        behaviors[alg] = np.asarray(state.repertoire.behaviors[:n])
        lines.append(f"| {alg} | {float(m['coverage'][-1]):.3f} | {float(m['mean_quality'][-1]):.3f} | {n} "
                     f"| {int(m['num_evaluations'][-1])} | {compile_s:.1f} | {run_s:.1f} |")
        print(lines[-1], flush=True)
    report.write(lines, os.path.join(args.out, f"robot_{args.task}.md"))
    _plot(behaviors, os.path.join(args.out, f"robot_{args.task}.png"), args.task)


def _plot(behaviors: dict[str, np.ndarray], path: str, task: str) -> None:
    plt = report.pyplot()
    if plt is None:
        return
    fig, axes = plt.subplots(1, len(behaviors), figsize=(5 * len(behaviors), 5))
    for ax, (alg, b) in zip(np.atleast_1d(axes), behaviors.items(), strict=True):
        plots.repertoire(ax, registry.make(task), b, f"{task}: {alg}")
    plots.save(fig, path)


if __name__ == "__main__":
    main()
