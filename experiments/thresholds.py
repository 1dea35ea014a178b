"""M-QD's filter thresholds: final coverage and evaluations over a (t_nov, t_qua) grid, against QD.

    python experiments/thresholds.py [--task obstacle2d] [--seeds 5] [--t-nov 0 0.02 0.04 0.08]
                                     [--t-qua 0 0.05 1] [--out results/thresholds]

The paper says t_nov and t_qua "need to be chosen carefully" and gives no
guidance. Every (t_nov, t_qua) pair and seed runs in ONE compiled, vmapped
M-QD call (the thresholds are the traced parameters of "mqd-paper"'s `Threshold`; `mqd_jax.experiment.sweep.grid`),
sharded over the devices; QD runs the same seeds in a second call. Defaults:
the task's Table II settings. Writes thresholds_<task>.json (per setting: final
coverage and evaluations per seed), thresholds_<task>.md (means; QD's coverage
after as many evaluations as each setting spent, interpolated between
generations: M-QD is more sample-efficient where it is ahead of that) and
thresholds_<task>.png (final coverage against evaluations per setting, with
one-std bars, over QD's mean coverage curve).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import report

from mqd_jax import Config
from mqd_jax.experiment import plots
from mqd_jax.experiment.folders import write_json
from mqd_jax.experiment.sweep import grid, run_batch, seed_keys


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="obstacle2d")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--generations", type=int, default=None, help="default: Table II")
    parser.add_argument("--t-nov", type=float, nargs="+", default=[0.0, 0.02, 0.04, 0.08])
    parser.add_argument("--t-qua", type=float, nargs="+", default=[0.0, 0.05, 1.0])
    parser.add_argument("--out", default="results/thresholds")
    args = parser.parse_args()
    extra = {} if args.generations is None else {"max_generations": args.generations}
    mqd = Config.paper(args.task, algorithm="mqd-paper", **extra)
    start = time.perf_counter()
    _, qd = run_batch(Config.paper(args.task, algorithm="qd", **extra), seed_keys(args.seeds))
    qd_s = time.perf_counter() - start
    thresholds = {"emitter.acquisition.t_nov": args.t_nov, "emitter.acquisition.t_qua": args.t_qua}
    keys, params, pairs = grid(mqd, thresholds, args.seeds)
    start = time.perf_counter()
    _, runs = run_batch(mqd, keys, params)
    grid_s = time.perf_counter() - start
    shape = (len(pairs), args.seeds)
    coverage = runs["coverage"][:, -1].reshape(shape)
    spent = runs["num_evaluations"][:, -1].reshape(shape)
    qd_cov, qd_evals = qd["coverage"], qd["num_evaluations"]
    lines = [f"{args.task}, Table II settings, {mqd.max_generations} generations, {args.seeds} seeds (means); "
             f"{report.machine()}. All {len(pairs)} settings x {args.seeds} seeds in one vmapped call: {grid_s:.0f} s "
             f"(QD's {args.seeds} seeds: {qd_s:.0f} s; compilation included). QD: final coverage "
             f"{qd_cov[:, -1].mean():.3f} +- {qd_cov[:, -1].std():.3f} after {qd_evals[0, -1]:.0f} evaluations.", "",
             "| t_nov | t_qua | M-QD coverage | M-QD evaluations | QD coverage at these evaluations |",
             "|---|---|---|---|---|"]
    for (t_nov, t_qua), cov, ev in zip(pairs, coverage, spent, strict=True):
        at = report.coverage_at(qd_evals, qd_cov, ev.mean()).mean()
        lines.append(f"| {t_nov} | {t_qua} | {cov.mean():.3f} +- {cov.std():.3f} | {ev.mean():.0f} | {at:.3f} |")
    os.makedirs(args.out, exist_ok=True)
    stem = os.path.join(args.out, f"thresholds_{args.task}")
    report.write(lines, stem + ".md")
    write_json(stem + ".json", {"task": args.task, "pairs": pairs, "coverage": coverage, "evaluations": spent,
                                "qd_coverage": qd_cov, "qd_evaluations": qd_evals})
    _plot(args.task, pairs, coverage, spent, qd_evals, qd_cov, stem + ".png")


def _plot(task: str, pairs: list[tuple[float, float]], coverage: np.ndarray, spent: np.ndarray,
          qd_evals: np.ndarray, qd_cov: np.ndarray, path: str) -> None:
    plt = report.pyplot()
    if plt is None:
        return
    fig, ax = plt.subplots(figsize=(7, 5))
    x, mean, std = qd_evals.mean(0), qd_cov.mean(0), qd_cov.std(0)
    ax.plot(x, mean, c="k", label="QD (coverage during the run)")
    ax.fill_between(x, mean - std, mean + std, color="k", alpha=0.15)
    t_novs = sorted({p[0] for p in pairs})
    t_quas = sorted({p[1] for p in pairs})
    colours = plt.cm.viridis(np.linspace(0, 0.9, len(t_novs)))
    markers = "osD^v<>"
    for (t_nov, t_qua), cov, ev in zip(pairs, coverage, spent, strict=True):
        ax.errorbar(ev.mean(), cov.mean(), xerr=ev.std(), yerr=cov.std(), fmt=markers[t_quas.index(t_qua) % 7],
                    c=colours[t_novs.index(t_nov)], capsize=3, label=f"M-QD t_nov {t_nov}, t_qua {t_qua}")
    ax.set(xlabel="evaluations", ylabel="final coverage (M-QD) / coverage (QD)", title=f"{task}: filter thresholds")
    ax.legend(fontsize=7, ncol=2)
    plots.save(fig, path)


if __name__ == "__main__":
    main()
