"""Where a generation's time goes: each stage of `run.generation`, jitted alone, on a grown repertoire.

    python experiments/profile_generation.py [--task obstacle2d] [--algorithm mqd] [--grow 250]

Runs `--grow` generations first (paper 2D settings), then times, from that
state, the whole generation and its stages as separately jitted functions
(median of `--repeats` calls): ask (the emitter's proposal: variation and, for
M-QD, the model's acquisition), rollouts, insertion (distance matrix, nearest-skill search,
sequential rule, neighbour lists, novelty), coverage stamp and model training.
Stages timed alone do not add up exactly to the fused generation.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import report

from mqd_jax import Config, ModelEmitter, init
from mqd_jax.core import coverage, repertoire
from mqd_jax.core.run import ask, generation, run_generations
from mqd_jax.core.state import get_task


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="obstacle2d")
    parser.add_argument("--algorithm", default="qd", choices=["qd", "mqd", "mqd-paper", "random"])
    parser.add_argument("--grow", type=int, default=250)
    parser.add_argument("--repeats", type=int, default=200)
    args = parser.parse_args()
    cfg = Config.paper_2d(task=args.task, algorithm=args.algorithm)
    params, task = cfg.params(), get_task(cfg)
    grow = jax.jit(run_generations, static_argnums=(1, 3))
    state, _ = grow(init(jax.random.PRNGKey(0), cfg), cfg, params, args.grow)
    key = jax.random.PRNGKey(1)
    proposal = ask(state, cfg, params)
    b, q, ok = task.evaluate(proposal.actions, key)
    ok = ok & proposal.rollout
    stages = {
        "whole generation": jax.jit(lambda s: generation(s, cfg, params)),
        "ask (variation, acquisition)": jax.jit(lambda s: ask(s, cfg, params)),
        "rollouts": jax.jit(lambda s: task.evaluate(proposal.actions, key)),
        "insertion (incl. neighbours, novelty)": jax.jit(lambda s: repertoire.insert(
            s.repertoire, proposal.actions, b, q, ok, params.t_dist, cfg.k, repertoire.NUM_NEAR, chunk=32,
            features=proposal.features)),
        "coverage stamp": jax.jit(lambda s: coverage.stamp(s.coverage, b, ok.astype(jnp.int32), params.t_dist)),
    }
    emitter = cfg.emitter
    if isinstance(emitter, ModelEmitter):
        steps = getattr(emitter.surrogate, "num_batches", None)  # the surrogate's `fit`, its features included
        stages["model training" + (f" ({steps} Adam steps)" if steps else "")] = jax.jit(
            lambda s: emitter.model.fit(key, s.emitter.surrogate, s.repertoire, task, params.emitter.surrogate))
    print(f"{args.task}, {args.algorithm}, repertoire of {int(state.repertoire.count)} skills after {args.grow} "
          f"generations (capacity {cfg.capacity}); {report.machine()}; median of {args.repeats} calls.\n")
    print("| stage | ms |\n|---|---|")
    for name, fn in stages.items():
        print(f"| {name} | {report.median_ms(lambda f=fn: f(state), args.repeats):.3f} |", flush=True)


if __name__ == "__main__":
    main()
