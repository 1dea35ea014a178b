"""Diverse's two selections against each other: ms per choice and niches opened, on random pools.

    python experiments/selection_timing.py [--populations 100 256 512 1024 2048 4096] [--rounds 16]

A pool of 8 x population uniform predicted behaviors in [0, 1]^2 beside 300 random skills (t_dist 0.02,
quality_share 0.1, every candidate wanted): the median of 3 jitted calls (compile excluded) of `greedy_diverse`
(one at a time) and `rounds_diverse`, and how many niches each choice opens (brute force, in order). What sets
`diverse.ROUNDS_FROM`.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
import report

from mqd_jax.emitters.acquisition import Judged
from mqd_jax.emitters.diverse import greedy_diverse, rounds_diverse


def opened(b: np.ndarray, rows: np.ndarray, skills: np.ndarray, t_dist: float) -> int:
    """How many rows, in order, lie farther than t_dist from every skill and every row before them."""
    held, count = list(skills), 0
    for x in b[rows]:
        count += bool(np.min(np.linalg.norm(np.asarray(held) - x, axis=1)) > t_dist)
        held.append(x)
    return count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--populations", type=int, nargs="+", default=[100, 256, 512, 1024, 2048, 4096])
    parser.add_argument("--rounds", type=int, default=16)
    args = parser.parse_args()
    print(f"{report.machine()}; pools of 8 x population in [0, 1]^2, 300 skills, t_dist 0.02, median of 3, ms")
    print("| population | greedy ms | rounds ms | greedy opened | rounds opened |\n|---|---|---|---|---|")
    t = jnp.float32(0.02)
    for population in args.populations:
        n = 8 * population
        k1, k2, k3 = jax.random.split(jax.random.PRNGKey(population), 3)
        b, skills = jax.random.uniform(k1, (n, 2)), jax.random.uniform(k2, (300, 2))
        d = jnp.sqrt(((b[:, None] - skills[None]) ** 2).sum(-1)).min(1)
        zero = jnp.zeros(n)
        pool = Judged(b, jax.random.uniform(k3, (n,)), zero, d, zero, zero, zero)
        wanted = jnp.ones(n, bool)
        greedy = jax.jit(lambda p: greedy_diverse(p, wanted, t, 1.0, population, quality_share=0.1))  # noqa: B023
        rounds = jax.jit(lambda p: rounds_diverse(p, wanted, t, 1.0, population, args.rounds,  # noqa: B023
                                                  quality_share=0.1))
        cells = [report.median_ms(lambda f=f, pool=pool: f(pool), 3) for f in (greedy, rounds)]
        found = [opened(np.asarray(b), np.asarray(f(pool)), np.asarray(skills), 0.02) for f in (greedy, rounds)]
        print(f"| {population} | {cells[0]:.2f} | {cells[1]:.2f} | {found[0]} | {found[1]} |", flush=True)


if __name__ == "__main__":
    main()
