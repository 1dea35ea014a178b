"""The `mqd` command line: `mqd run` runs one search with a progress line per chunk."""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings

import jax
import numpy as np

from mqd_jax.config import Config
from mqd_jax.run import init, run_generations


def _run(args: argparse.Namespace) -> None:
    cfg = Config.paper_2d(task=args.task, algorithm=args.algorithm, max_generations=args.generations,
                          population_size=args.population, capacity=args.capacity)
    chunk = max(1, min(args.chunk, cfg.max_generations))
    step = jax.jit(run_generations, static_argnums=(1, 3))
    state, params = init(jax.random.PRNGKey(args.seed), cfg), cfg.params()
    history: list[dict[str, np.ndarray]] = []
    start = time.perf_counter()
    done = 0
    while done < cfg.max_generations:
        n = min(chunk, cfg.max_generations - done)
        state, m = step(state, cfg, params, n)
        history.append(jax.tree.map(np.asarray, m))
        done += n
        print(f"generation {done:4d}  coverage {m['coverage'][-1]:.3f}  size {int(m['repertoire_size'][-1]):5d}  "
              f"evaluations {int(m['num_evaluations'][-1]):7d}  {done / (time.perf_counter() - start):.1f} gen/s",
              flush=True)
    metrics = {k: np.concatenate([h[k] for h in history]) for k in history[0]}
    dropped = int(metrics["dropped_full"].sum())
    if dropped:
        warnings.warn(f"{dropped} new niches did not fit: raise --capacity above {cfg.capacity}", stacklevel=1)
    print(f"done: coverage {metrics['coverage'][-1]:.3f}, mean quality {metrics['mean_quality'][-1]:.3f}, "
          f"{int(state.repertoire.count)} skills, {int(metrics['num_evaluations'][-1])} evaluations, "
          f"{time.perf_counter() - start:.1f} s (compilation included)")
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "metrics.json"), "w") as f:
        json.dump({k: v.tolist() for k, v in metrics.items()}, f)
    n = int(state.repertoire.count)
    np.savez(os.path.join(args.out, "repertoire.npz"), actions=np.asarray(state.repertoire.actions[:n]),
             behaviors=np.asarray(state.repertoire.behaviors[:n]), qualities=np.asarray(state.repertoire.qualities[:n]))
    _plot(metrics, np.asarray(state.repertoire.behaviors[:n]), os.path.join(args.out, "run.png"))


def _plot(metrics: dict[str, np.ndarray], behaviors: np.ndarray, path: str) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed (pip install -e .[plot]): no plot written")
        return
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 4))
    ax1.plot(metrics["num_evaluations"], metrics["coverage"])
    ax1.set(xlabel="evaluations", ylabel="coverage")
    ax2.scatter(behaviors[:, 0], behaviors[:, 1], s=2)
    ax2.set(xlabel="behavior x", ylabel="behavior y", aspect="equal")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    print(f"wrote {path}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="mqd", description="Model-Based Quality-Diversity search in JAX")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run one search and write metrics, repertoire and a plot")
    run.add_argument("--task", default="obstacle2d")
    run.add_argument("--algorithm", default="qd", choices=["mqd", "qd", "random"])
    run.add_argument("--generations", type=int, default=100)
    run.add_argument("--population", type=int, default=100)
    run.add_argument("--capacity", type=int, default=4096)
    run.add_argument("--seed", type=int, default=0)
    run.add_argument("--chunk", type=int, default=25, help="generations per compiled chunk (one progress line)")
    run.add_argument("--out", default="results/run")
    args = parser.parse_args(argv)
    try:
        _run(args)
    except ValueError as e:  # invalid configuration: say what, not a traceback
        parser.error(str(e))


if __name__ == "__main__":
    main()
