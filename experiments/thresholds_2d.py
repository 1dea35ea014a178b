"""M-QD's filter thresholds: coverage and evaluations over a (t_nov, t_qua) grid, against QD.

    python experiments/thresholds_2d.py [--task obstacle2d] [--seeds 5] [--out results/thresholds_obstacle2d.md]

One compiled M-QD run (the thresholds are traced `Params`) is run for every
grid point and seed, and one compiled QD run per seed. For each setting the
table gives the final coverage, the evaluations spent, QD's coverage after as
many evaluations (interpolated between generations), and both algorithms'
coverage after 10,000 evaluations: M-QD is more sample-efficient where its
coverage beats QD's at equal evaluations.
"""

from __future__ import annotations

import argparse
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import report

from mqd_jax import Config, run_mqd


def _coverage_at(runs: list[dict[str, jax.Array]], evaluations: float) -> float:
    """Mean over runs of the coverage once `evaluations` evaluations were spent."""
    stack = lambda name: np.stack([np.asarray(m[name]) for m in runs])  # noqa: E731
    return float(report.coverage_at(stack("num_evaluations"), stack("coverage"), evaluations).mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="obstacle2d")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--generations", type=int, default=250)
    parser.add_argument("--t-nov", type=float, nargs="*", default=[0.0, 0.02, 0.04, 0.08])
    parser.add_argument("--t-qua", type=float, nargs="*", default=[0.0, 0.05, 1.0])
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    out = args.out or f"results/thresholds_{args.task}.md"
    keys = jax.random.split(jax.random.PRNGKey(0), args.seeds)
    compiled = {}
    for alg in ("qd", "mqd"):
        cfg = Config.paper_2d(task=args.task, algorithm=alg, max_generations=args.generations)
        compiled[alg] = cfg, run_mqd.lower(keys[0], cfg, cfg.params()).compile()
    qd_cfg, qd_run = compiled["qd"]
    qd = [qd_run(k, qd_cfg.params())[1] for k in keys]
    lines = [f"{args.task}, paper 2D settings, {args.generations} generations, {args.seeds} seeds (means); "
             f"{report.machine()}. "
             f"QD: final coverage {np.mean([float(m['coverage'][-1]) for m in qd]):.3f} after "
             f"{int(qd[0]['num_evaluations'][-1])} evaluations.", "",
             "| t_nov | t_qua | M-QD coverage | M-QD evaluations | QD coverage at these evaluations "
             "| M-QD coverage at 10k | QD coverage at 10k |", "|---|---|---|---|---|---|---|"]
    mqd_cfg, mqd_run = compiled["mqd"]
    for t_nov, t_qua in itertools.product(args.t_nov, args.t_qua):
        params = mqd_cfg.params().replace(t_nov=jnp.float32(t_nov), t_qua=jnp.float32(t_qua))
        runs = [mqd_run(k, params)[1] for k in keys]
        spent = float(np.mean([int(m["num_evaluations"][-1]) for m in runs]))
        lines.append(f"| {t_nov} | {t_qua} | {np.mean([float(m['coverage'][-1]) for m in runs]):.3f} | {spent:.0f} "
                     f"| {_coverage_at(qd, spent):.3f} | {_coverage_at(runs, 1e4):.3f} | {_coverage_at(qd, 1e4):.3f} |")
        print(lines[-1], flush=True)
    report.write(lines, out)


if __name__ == "__main__":
    main()
