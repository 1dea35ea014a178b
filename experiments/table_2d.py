"""Final coverage and mean quality of QD and RANDOM on the 2D tasks (paper settings).

    python experiments/table_2d.py [--seeds 3] [--generations 250] [--out results/table_2d.md]

Seeds are vmapped in one compiled call per (task, algorithm). Prints and writes
a markdown table with mean +- std over seeds, the wall time of the vmapped
sweep and of one single run.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax
import numpy as np

from mqd_jax import Config, run_mqd


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--generations", type=int, default=250)
    parser.add_argument("--tasks", nargs="*", default=["obstacle2d", "object2d"])
    parser.add_argument("--algorithms", nargs="*", default=["qd", "random"])
    parser.add_argument("--out", default="results/table_2d.md")
    args = parser.parse_args()
    keys = jax.random.split(jax.random.PRNGKey(0), args.seeds)
    lines = [f"Paper 2D settings, {args.generations} generations, {args.seeds} seeds; "
             f"{platform.machine()}, {os.cpu_count()} CPU cores, jax {jax.__version__} on {jax.default_backend()}.",
             "", "| task | algorithm | coverage | mean quality | repertoire size | evaluations | dropped (full) "
             "| one run, s | all seeds vmapped, s |", "|---|---|---|---|---|---|---|---|---|"]
    for task in args.tasks:
        for alg in args.algorithms:
            cfg = Config.paper_2d(task=task, algorithm=alg, max_generations=args.generations)
            one = run_mqd.lower(keys[0], cfg).compile()
            start = time.perf_counter()
            jax.block_until_ready(one(keys[0]))
            single_s = time.perf_counter() - start
            sweep = jax.jit(jax.vmap(lambda k, c=cfg: run_mqd(k, c))).lower(keys).compile()
            start = time.perf_counter()
            _, m = jax.block_until_ready(sweep(keys))
            sweep_s = time.perf_counter() - start
            cov, qual = np.asarray(m["coverage"][:, -1]), np.asarray(m["mean_quality"][:, -1])
            dropped = int(np.asarray(m["dropped_full"]).sum())
            if dropped:
                print(f"warning: {dropped} new niches dropped: raise Config.capacity above {cfg.capacity}")
            lines.append(f"| {task} | {alg} | {cov.mean():.3f} +- {cov.std():.3f} | {qual.mean():.3f} +- "
                         f"{qual.std():.3f} | {np.asarray(m['repertoire_size'][:, -1]).mean():.0f} "
                         f"| {int(m['num_evaluations'][0, -1])} | {dropped} | {single_s:.1f} | {sweep_s:.1f} |")
            print(lines[-1], flush=True)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
