"""Do two versions of the code give the same runs? Saves runs to a file, or compares runs with a saved file.

    python experiments/same_results.py --save results/before.npz     # with the old code
    python experiments/same_results.py --compare results/before.npz  # with the new code: a table

Runs 2D Obstacle (Table II's 2D settings, `--generations`) for each `--algorithms` preset at each
`--populations` size (capacity max(4096, population)), seed 0, and keeps every metric per generation
and the final repertoire (actions, behaviors, qualities). `--compare` says, per run, whether every
array is bit for bit the same, and the largest coverage difference at any generation.
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np
import report

from mqd_jax import Config, run_mqd


def runs(args: argparse.Namespace) -> dict[str, np.ndarray]:
    """{"<algorithm>/<population>/<name>": array} of every run."""
    out = {}
    for algorithm in args.algorithms:
        for population in args.populations:
            cfg = Config.paper_2d(task="obstacle2d", algorithm=algorithm, population_size=population,
                                  capacity=max(4096, population), max_generations=args.generations)
            state, metrics = jax.device_get(run_mqd(jax.random.PRNGKey(0), cfg))
            n = int(state.repertoire.count)
            arrays = {f"metrics.{k}": np.asarray(v) for k, v in metrics.items()}
            arrays.update({f"repertoire.{k}": np.asarray(getattr(state.repertoire, k))[:n]
                           for k in ("actions", "behaviors", "qualities")})
            out.update({f"{algorithm}/{population}/{k}": v for k, v in arrays.items()})
            print(f"{algorithm} population {population}: coverage {float(metrics['coverage'][-1]):.4f}", flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algorithms", nargs="+", default=["qd", "random", "mqd"])
    parser.add_argument("--populations", type=int, nargs="+", default=[100, 1024])
    parser.add_argument("--generations", type=int, default=100)
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--save")
    which.add_argument("--compare")
    parser.add_argument("--out", default="results/same_results.md")
    args = parser.parse_args()
    now = runs(args)
    if args.save:
        np.savez_compressed(args.save, about=np.asarray(json.dumps({"machine": report.machine()})), **now)
        return
    with np.load(args.compare) as f:
        before = {k: f[k] for k in f.files if k != "about"}
    lines = [f"2D Obstacle, {args.generations} generations, seed 0; {report.machine()}; against {args.compare}.", "",
             "| algorithm | population | every array bit for bit | arrays that differ | largest coverage difference |",
             "|---|---|---|---|---|"]
    for algorithm in args.algorithms:
        for population in args.populations:
            prefix = f"{algorithm}/{population}/"
            names = sorted(k for k in before if k.startswith(prefix))
            differ = [k[len(prefix):] for k in names if k not in now or not np.array_equal(now[k], before[k])]
            gap = np.abs(now[prefix + "metrics.coverage"] - before[prefix + "metrics.coverage"]).max()
            lines.append(f"| {algorithm} | {population} | {'yes' if not differ else 'no'} | "
                         f"{', '.join(differ) or '-'} | {gap:.4f} |")
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
