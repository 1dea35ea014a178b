"""ms per generation against the population, for this checkout or an older one (it uses only what 0.9 had).

    python experiments/population_scaling.py [--populations 100 1024 4096] [--algorithms qd mqd] [--whole 50]
        [--out results/population_scaling.md]
    PYTHONPATH=OLD_CHECKOUT:experiments python experiments/population_scaling.py ...   # the same, older code

2D Obstacle, Table II's 2D settings, capacity max(4096, population): a chunk of `--generations`
generations (one compiled `lax.scan`) from a state grown `--grow` generations, median of `--repeats`
calls, compile excluded; each population's time and its ratio to the first population's, and each
algorithm's ratio to the first algorithm's at the same population. Beside it, what a user pays: a whole run of
`--whole` generations from an empty repertoire (one compiled chunk from `init`, median of `--repeats`, compile
excluded), per generation, with the same two ratios (0: not measured).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

import jax
import report

import mqd_jax
from mqd_jax import Config, init
from mqd_jax.core.run import run_generations


def grown(algorithm: str, population: int, args: argparse.Namespace) -> tuple[Config, Any, Callable, Any]:
    """(config, params, the jitted chunk `(state, cfg, params, num) -> (state, metrics)`, a state grown
    `args.grow` generations) of 2D Obstacle at `population`, capacity max(4096, population)."""
    cfg = Config.paper_2d(task="obstacle2d", algorithm=algorithm, population_size=population,
                          capacity=max(4096, population), archive_capacity=max(4096, population),
                          max_generations=max(args.grow + args.generations, getattr(args, "whole", 0)))
    params = cfg.params()
    chunk = jax.jit(run_generations, static_argnums=(1, 3))
    state = jax.block_until_ready(chunk(init(jax.random.PRNGKey(0), cfg), cfg, params, args.grow)[0])
    return cfg, params, chunk, state


def ms_per_generation(algorithm: str, population: int, args: argparse.Namespace) -> tuple[float, float]:
    """ms per generation (from the grown state; of a whole run of `args.whole` generations from an empty
    repertoire, NaN if 0)."""
    cfg, params, chunk, state = grown(algorithm, population, args)
    ms = report.median_ms(lambda: chunk(state, cfg, params, args.generations), args.repeats) / args.generations
    return ms, whole_run_ms(cfg, params, chunk, args.whole, args.repeats)


def whole_run_ms(cfg: Config, params: Any, chunk: Callable, generations: int, repeats: int) -> float:
    """ms per generation of a run of `generations` from an empty repertoire (as a user starts one), compile
    excluded, median of `repeats`; NaN for 0 generations."""
    if not generations:
        return float("nan")
    empty = jax.block_until_ready(init(jax.random.PRNGKey(0), cfg))
    return report.median_ms(lambda: chunk(empty, cfg, params, generations), repeats) / generations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--populations", type=int, nargs="+", default=[100, 1024, 4096])
    parser.add_argument("--algorithms", nargs="+", default=["qd", "mqd"])
    parser.add_argument("--grow", type=int, default=20)
    parser.add_argument("--generations", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--whole", type=int, default=50, help="generations of a whole run from empty (0: none)")
    parser.add_argument("--out", default="results/population_scaling.md")
    args = parser.parse_args()
    lines = [f"mqd-jax {mqd_jax.__version__}; {report.machine()}; 2D Obstacle, a chunk of {args.generations} "
             f"generations after {args.grow}, and a whole run of {args.whole} generations from an empty repertoire; "
             f"median of {args.repeats}, compile excluded.", "",
             "| algorithm | population | grown: ms / generation | vs first population | vs first algorithm | "
             "whole run: ms / generation | vs first population | vs first algorithm |",
             "|---|---|---|---|---|---|---|---|"]
    found: dict[tuple[str, int], tuple[float, float]] = {}
    for algorithm in args.algorithms:
        for population in args.populations:
            found[algorithm, population] = ms_per_generation(algorithm, population, args)
            cells = [f"{ms:.2f} | {ms / found[algorithm, args.populations[0]][i]:.1f} | "
                     f"{ms / found[args.algorithms[0], population][i]:.1f}"
                     for i, ms in enumerate(found[algorithm, population])]
            lines.append(f"| {algorithm} | {population} | {' | '.join(cells)} |")
            report.write(lines, args.out)


if __name__ == "__main__":
    main()
