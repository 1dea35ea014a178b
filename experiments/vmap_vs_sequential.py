"""Wall time of a seed sweep: all seeds vmapped in one compiled call vs the same seeds run one by one.

    python experiments/vmap_vs_sequential.py [--task obstacle2d] [--seeds 25] [--algorithms qd mqd]

Paper 2D settings. The vmapped sweep is `mqd_jax.experiment.sweep.run_batch` (what `mqd
sweep` runs), timed on its second call; the sequential one is a compiled
`run_mqd` called once per key. Compilation is excluded from both; each time
is the fastest of `--repeats` alternating measurements.
Also reports how far the two sweeps' final coverages are apart: a vmapped program
rounds some operations differently, and single runs drift apart after tens of
generations, so the sweeps agree in distribution, not run by run.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np
import report

from mqd_jax import Config, run_mqd
from mqd_jax.experiment.sweep import run_batch, seed_keys


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="obstacle2d")
    parser.add_argument("--seeds", type=int, default=25)
    parser.add_argument("--algorithms", nargs="*", default=["qd", "mqd"])
    parser.add_argument("--repeats", type=int, default=2, help="timings: the fastest of this many")
    parser.add_argument("--out", default="results/vmap_vs_sequential.md")
    args = parser.parse_args()
    keys = seed_keys(args.seeds)
    lines = [f"{args.task}, paper 2D settings, {args.seeds} seeds; {report.machine()}.", "",
             "| algorithm | sequential s | vmapped s | vmapped / sequential | mean coverage, sequential | vmapped |",
             "|---|---|---|---|---|---|"]
    for alg in args.algorithms:
        cfg = Config.paper_2d(task=args.task, algorithm=alg)
        params = cfg.params()
        one = jax.jit(run_mqd, static_argnames="cfg").lower(keys[0], cfg, params).compile()
        run_batch(cfg, keys)  # compiles
        seq_s, vm_s = [], []
        for _ in range(args.repeats):  # alternating, so that a slow spell of the machine hits both
            start = time.perf_counter()
            seq = [float(jax.block_until_ready(one(k, params))[1]["coverage"][-1]) for k in keys]
            seq_s.append(time.perf_counter() - start)
            start = time.perf_counter()
            vm = run_batch(cfg, keys)[1]["coverage"][:, -1]
            vm_s.append(time.perf_counter() - start)
        seq_s, vm_s = min(seq_s), min(vm_s)
        lines.append(f"| {alg} | {seq_s:.1f} | {vm_s:.1f} | {vm_s / seq_s:.2f} "
                     f"| {np.mean(seq):.3f} +- {np.std(seq):.3f} | {vm.mean():.3f} +- {vm.std():.3f} |")
        print(lines[-1], flush=True)
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
