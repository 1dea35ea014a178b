"""Seed sweeps of M-QD, QD and RANDOM (the paper's Table I and Figure 2), vmapped and sharded over devices.

    python experiments/sweep.py [--tasks obstacle2d object2d] [--seeds 25] [--generations 250]
                                [--algorithms mqd qd random] [--out results/sweep]

For each task and algorithm, all seeds run as one compiled `jax.vmap` of
`run_mqd`, with the seed axis sharded over every local device (a `Mesh` over
the seed axis; seeds are padded to a multiple of the device count). The same
script runs on one CPU or on eight GPUs; on several hosts, start it on every
host after `jax.distributed.initialize()` and the mesh spans all their devices.
Defaults: Table II settings (the robot tasks take the robot column, 100
generations) and the paper's 25 seeds; `--seeds`/`--generations` shrink a run.

Writes to `--out`: metrics_<task>_<algorithm>.json (every metric, [seeds,
generations]), table1.md (final coverage and mean quality, mean +- std, the
paper's coverage, and two-sided Mann-Whitney p-values of M-QD vs QD and QD vs
RANDOM on final coverage), and, with matplotlib, fig2_<task>.png (coverage
against evaluations (x: the mean evaluations at each generation), mean and one std
band, and seed 0's final repertoire of each algorithm over the behavior box).
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import numpy as np
import report
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from mqd_jax import Config, run_mqd
from mqd_jax.stats import mann_whitney

PAPER_COVERAGE = {  # Table I: M-QD, QD, RANDOM
    "obstacle2d": (0.971, 0.875, 0.731), "object2d": (0.504, 0.366, 0.035), "push_cube": (0.828, 0.709, 0.216),
    "push_sphere": (0.685, 0.560, 0.171), "place": (0.639, 0.524, 0.349),
}
ROBOT = {"push_cube", "push_sphere", "place"}


def sweep(cfg: Config, seeds: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Per-generation metrics [seeds, G] of `seeds` runs in one sharded, vmapped call, and the final behaviors
    of seed 0 [count, d]."""
    devices = jax.devices()
    padded = -(-seeds // len(devices)) * len(devices)
    keys = jax.random.split(jax.random.PRNGKey(0), padded)
    keys = jax.device_put(keys, NamedSharding(Mesh(np.array(devices), ("seed",)), PartitionSpec("seed")))
    states, metrics = jax.jit(jax.vmap(lambda k: run_mqd(k, cfg)))(keys)
    count = int(states.repertoire.count[0])
    return ({k: np.asarray(v)[:seeds] for k, v in metrics.items()},
            np.asarray(states.repertoire.behaviors[0, :count]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="*", default=["obstacle2d", "object2d"])
    parser.add_argument("--algorithms", nargs="*", default=["mqd", "qd", "random"])
    parser.add_argument("--seeds", type=int, default=25)
    parser.add_argument("--generations", type=int, default=None, help="default: Table II (250 2D, 100 robot)")
    parser.add_argument("--out", default="results/sweep")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    lines = [f"{args.seeds} seeds, Table II settings; {report.machine()}, {len(jax.devices())} device(s). "
             "p: two-sided Mann-Whitney U on final coverage.", "",
             "| task | algorithm | coverage | mean quality | evaluations | paper coverage | p vs next |",
             "|---|---|---|---|---|---|---|"]
    for task in args.tasks:
        preset = Config.paper_robot if task in ROBOT else Config.paper_2d
        final, curves, shown = {}, {}, {}
        for alg in args.algorithms:
            overrides = {} if args.generations is None else {"max_generations": args.generations}
            metrics, behaviors = sweep(preset(task=task, algorithm=alg, **overrides), args.seeds)
            with open(os.path.join(args.out, f"metrics_{task}_{alg}.json"), "w") as f:
                json.dump({k: np.where(np.isnan(v), None, v).tolist() for k, v in metrics.items()}, f)
            final[alg] = metrics
            curves[alg] = (metrics["num_evaluations"], metrics["coverage"])
            shown[alg] = behaviors
        order = [a for a in ("mqd", "qd", "random") if a in final]
        for i, alg in enumerate(order):
            m = final[alg]
            cov, qual = m["coverage"][:, -1], m["mean_quality"][:, -1]
            paper = PAPER_COVERAGE.get(task, (None,) * 3)[("mqd", "qd", "random").index(alg)]
            p = f"{mann_whitney(cov, final[order[i + 1]]['coverage'][:, -1])[1]:.2g} (vs {order[i + 1]})" \
                if i + 1 < len(order) else ""
            lines.append(f"| {task} | {alg} | {cov.mean():.3f} +- {cov.std():.3f} | {qual.mean():.3f} +- "
                         f"{qual.std():.3f} | {m['num_evaluations'][:, -1].mean():.0f} | {paper or ''} | {p} |")
            print(lines[-1], flush=True)
        _figure(task, curves, shown, os.path.join(args.out, f"fig2_{task}.png"))
    report.write(lines, os.path.join(args.out, "table1.md"))


def _figure(task: str, curves: dict, shown: dict, path: str) -> None:
    plt = report.pyplot()
    if plt is None:
        return
    import envs

    box = envs.make(task)
    fig, axes = plt.subplots(1, 1 + len(shown), figsize=(4.5 * (1 + len(shown)), 4))
    for alg, (evals, cov) in curves.items():
        x, mean, std = evals.mean(0), cov.mean(0), cov.std(0)
        axes[0].plot(x, mean, label=alg)
        axes[0].fill_between(x, mean - std, mean + std, alpha=0.25)
    axes[0].set(xlabel="evaluations", ylabel="coverage", title=task)
    axes[0].legend()
    for ax, (alg, b) in zip(axes[1:], shown.items(), strict=True):
        for x0, y0, x1, y1 in getattr(box, "obstacles", ()):
            ax.add_patch(plt.Rectangle((x0, y0), x1 - x0, y1 - y0, color="0.4"))
        ax.scatter(b[:, 0], b[:, 1], s=2)
        ax.set(xlim=(box.behavior_low[0], box.behavior_high[0]), ylim=(box.behavior_low[1], box.behavior_high[1]),
               aspect="equal", title=f"{alg}: {len(b)} skills (seed 0)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
