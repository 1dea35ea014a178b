"""Do two versions of the code give the same runs? Saves runs to a file, or compares runs with a saved file.

    python experiments/same_results.py --save results/before.npz     # with the old code
    python experiments/same_results.py --compare results/before.npz  # with the new code: a table
    python experiments/same_results.py --algorithms mqd mqd:step_aside=true mqd-paper:budgeted=true ...

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


def _prefix(algorithm: str, population: int, seed: int) -> str:
    """The names of a run's arrays start with this (seed 0's as the first files had them)."""
    return f"{algorithm}/{population}/" + (f"seed{seed}/" if seed else "")


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Bit for bit, NaN equal to NaN (a metric that is NaN where it does not apply, as model_loss in warm-up)."""
    return np.array_equal(a, b, equal_nan=a.dtype.kind == "f" and b.dtype.kind == "f")


def runs(args: argparse.Namespace) -> dict[str, np.ndarray]:
    """{"<algorithm>/<population>/<name>": array} of every run."""
    out = {}
    for algorithm in args.algorithms:
        for population in args.populations:
            name, _, given = algorithm.partition(":")  # a preset, or "name:option=value,..." (values as JSON)
            options = {k: json.loads(v) for k, v in (item.split("=", 1) for item in given.split(","))} if given else {}
            cfg = Config.paper_2d(task="obstacle2d", algorithm=name, algorithm_options=options,
                                  population_size=population, capacity=max(4096, population),
                                  max_generations=args.generations)
            for seed in range(args.seeds):
                state, metrics = jax.device_get(run_mqd(jax.random.PRNGKey(seed), cfg))
                n = int(state.repertoire.count)
                arrays = {f"metrics.{k}": np.asarray(v) for k, v in metrics.items()}
                arrays.update({f"repertoire.{k}": np.asarray(getattr(state.repertoire, k))[:n]
                               for k in ("actions", "behaviors", "qualities")})
                out.update({f"{_prefix(algorithm, population, seed)}{k}": v for k, v in arrays.items()})
                print(f"{algorithm} population {population} seed {seed}: coverage "
                      f"{float(metrics['coverage'][-1]):.4f}", flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algorithms", nargs="+", default=["qd", "random", "mqd"])
    parser.add_argument("--populations", type=int, nargs="+", default=[100, 1024])
    parser.add_argument("--generations", type=int, default=100)
    parser.add_argument("--seeds", type=int, default=1, help="seeds 0 .. N-1; more than 1: also the seeds' mean")
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
    lines = [f"2D Obstacle, {args.generations} generations, seeds 0-{args.seeds - 1}; {report.machine()}; against "
             f"{args.compare}. Seed 0's coverage, and (several seeds) the seeds' mean coverage: the largest "
             "difference at any generation, and the standard error of the difference of the means there.", "",
             "| algorithm | population | every array bit for bit | arrays that differ (seed 0) | largest coverage "
             "difference, seed 0 | of the seeds' mean (standard error) |", "|---|---|---|---|---|---|"]
    for algorithm in args.algorithms:
        for population in args.populations:
            prefix = _prefix(algorithm, population, 0)
            names = sorted(k for k in before if k.startswith(prefix) and "/seed" not in k)
            differ = [k[len(prefix):] for k in names if k not in now or not _same(now[k], before[k])]
            same = not differ and all(_same(now[k], before[k]) for k in before if k.startswith(prefix))
            gap = np.abs(now[prefix + "metrics.coverage"] - before[prefix + "metrics.coverage"]).max()
            curves = [np.stack([run[_prefix(algorithm, population, seed) + "metrics.coverage"]
                                for seed in range(args.seeds)]) for run in (now, before)]
            mean_gap = np.abs(curves[0].mean(0) - curves[1].mean(0))
            at = int(mean_gap.argmax())
            error = np.sqrt((curves[0][:, at].var(ddof=1) + curves[1][:, at].var(ddof=1)) / args.seeds) if (
                args.seeds > 1) else np.nan
            lines.append(f"| {algorithm} | {population} | {'yes' if same else 'no'} | {', '.join(differ) or '-'} | "
                         f"{gap:.4f} | {mean_gap[at]:.4f} ({error:.4f}) |")
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
