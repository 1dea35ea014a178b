"""The search's own timings on whatever JAX device this process has: the same command everywhere.

    python experiments/accelerator_timings.py [--populations 100 1024 4096 16384] [--algorithms qd mqd]
        [--seeds 25] [--robot-batches 1024 4096 16384] [--robot-backends mujoco mjx] [--out results/timings.md]

Three tables, each row written to `--out` as soon as it is measured:

1. Population (2D Obstacle, Table II's 2D settings, capacity max(4096, population)): ms per generation of
   each `--algorithms` preset from a state grown `--grow` generations (a chunk of `--generations`
   generations, one compiled `lax.scan`, median of `--repeats` calls after compiling) and in a whole run of
   `--whole` generations from an empty repertoire (what a user pays), each with its ratio to the
   smallest population's, the mean rounds of the parallel insertion, and the time of each named stage
   jitted alone on that state (`ask`: variation and the model's acquisition; `rollouts`; `insert`: the
   insertion rule, neighbour lists and novelty; `archive + coverage`; `update`: the emitter's, M-QD's
   training). Stages alone do not add up exactly to the fused generation.
2. A sweep: `--seeds` vmapped "mqd" runs of 2D Obstacle, 250 generations (`run_batch`): first call (with
   compiling) and a second call.
3. Robot (`--robot-task`, random actions): env-steps per second of each backend's `evaluate` per batch
   (`experiments/bench_physics.py`'s table).

The header names the host and the JAX device. docs/benchmarks.md holds the figures per machine.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import bench_physics
import jax
import jax.numpy as jnp
import numpy as np
import report
from population_scaling import grown, whole_run_ms

from mqd_jax import Config
from mqd_jax.core import repertoire
from mqd_jax.core.emitter import Evaluated
from mqd_jax.core.run import (
    _archive,
    _cover,
    _update_emitter,
    _usable,
    ask,
    get_task,
)
from mqd_jax.experiment.sweep import run_batch, seed_keys


def inserted(rep: Any, actions: jax.Array, b: jax.Array, q: jax.Array, usable: jax.Array, params: Any, cfg: Config,
             kept: dict[str, jax.Array]) -> Any:
    """The stage insert: `repertoire.insert` as a generation calls it (`kept`: the candidates' features)."""
    return repertoire.insert(rep, actions, b, q, usable, params.t_dist, cfg.k, repertoire.NUM_NEAR, chunk=32, **kept)


def generation_parts(state: Any, cfg: Config, params: Any) -> tuple[Any, ...]:
    """One generation's pieces from `state`, as `run.generation` makes them: (candidates, behaviors, qualities,
    usable, the insertion's extra arguments (the candidates' features; none in a checkout before 0.14), the
    repertoire after the insertion, the insertion, what the emitter's update sees)."""
    candidates = ask(state, cfg, params)
    b, q, ok, aux = get_task(cfg).evaluate_with_auxiliary(candidates.actions, candidates.key, candidates.rollout)
    b, q, usable = _usable(candidates, b, q, ok)
    kept = {"features": candidates.features} if hasattr(candidates, "features") else {}
    rep, ins = inserted(state.repertoire, candidates.actions, b, q, usable, params, cfg, kept)
    evaluated = Evaluated(b, q, usable, ins.status, jnp.where(usable[:, None], aux, 0.0).astype(jnp.float32))
    return candidates, b, q, usable, kept, rep, ins, evaluated


def population_row(algorithm: str, population: int, args: argparse.Namespace) -> dict[str, float]:
    """{"generation": ms, "rounds": mean insertion rounds, stage: ms} of `algorithm` at `population`."""
    cfg, params, chunk, state = grown(algorithm, population, args)
    task = get_task(cfg)
    _, metrics = chunk(state, cfg, params, args.generations)
    found = {"generation": report.median_ms(lambda: chunk(state, cfg, params, args.generations), args.repeats)
             / args.generations, "rounds": float(np.mean(np.asarray(metrics["insertion_rounds"]))),
             "whole": whole_run_ms(cfg, params, chunk, args.whole, args.repeats)}
    candidates, b, q, usable, kept, rep, ins, evaluated = generation_parts(state, cfg, params)
    stages = {
        "ask": jax.jit(lambda s: ask(s, cfg, params)),
        "rollouts": jax.jit(lambda s: task.evaluate_with_auxiliary(candidates.actions, candidates.key,
                                                                   candidates.rollout)),
        "insert": jax.jit(lambda s: inserted(s.repertoire, candidates.actions, b, q, usable, params, cfg, kept)),
        "archive + coverage": jax.jit(lambda s: (
            _archive(s.archive, s.repertoire, candidates.actions, evaluated, ins),
            _cover(s.coverage, s.repertoire, evaluated, ins, params.t_dist))),
        "update": jax.jit(lambda s: _update_emitter(jax.random.PRNGKey(1), s, candidates, evaluated, rep, cfg,
                                                    params)),
    }
    for name, fn in stages.items():
        found[name] = report.median_ms(lambda f=fn: f(state), args.repeats)
    return found


def sweep_seconds(seeds: int) -> tuple[float, float]:
    """(first call with compiling, second call) wall seconds of `seeds` vmapped "mqd" runs of 2D Obstacle."""
    cfg = Config.paper_2d(task="obstacle2d", algorithm="mqd")
    out = []
    for _ in range(2):
        start = time.perf_counter()
        jax.block_until_ready(run_batch(cfg, seed_keys(seeds))[0])
        out.append(time.perf_counter() - start)
    return out[0], out[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--populations", type=int, nargs="+", default=[100, 1024, 4096, 16384])
    parser.add_argument("--algorithms", nargs="*", default=["qd", "mqd"])
    parser.add_argument("--grow", type=int, default=20, help="generations run before timing")
    parser.add_argument("--generations", type=int, default=5, help="generations of the timed chunk")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--whole", type=int, default=50, help="generations of a whole run from empty (0: none)")
    parser.add_argument("--seeds", type=int, default=25, help="the sweep's seeds (0: no sweep)")
    parser.add_argument("--robot-task", default="push_cube")
    parser.add_argument("--robot-batches", type=int, nargs="*", default=[1024, 4096, 16384])
    parser.add_argument("--robot-backends", nargs="+", default=["mujoco", "mjx"])
    parser.add_argument("--out", default="results/accelerator_timings.md")
    args = parser.parse_args()
    lines = [f"{report.machine()}; JAX {jax.__version__}, device: {jax.devices()[0].device_kind} x "
             f"{jax.device_count()}.", ""]
    if args.algorithms:
        lines += [f"2D Obstacle, Table II's 2D settings (capacity max(4096, population)); a chunk of "
                  f"{args.generations} generations after {args.grow}, median of {args.repeats}, compile excluded; "
                  f"stages jitted alone, ms; a whole run of {args.whole} generations from an empty repertoire (what a "
                  "user pays), ms per generation.", "",
                  "| algorithm | population | ms / generation | vs smallest population | whole run: ms / generation "
                  "| vs smallest population | insertion rounds | ask | rollouts | insert | archive + coverage "
                  "| update |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for algorithm in args.algorithms:
        first = None
        for population in args.populations:
            row = population_row(algorithm, population, args)
            first = first or row
            lines.append(f"| {algorithm} | {population} | {row['generation']:.2f} | "
                         f"{row['generation'] / first['generation']:.1f} | {row['whole']:.2f} | "
                         f"{row['whole'] / first['whole']:.1f} | {row['rounds']:.1f} | " + " | ".join(
                             f"{row[s]:.2f}" for s in ("ask", "rollouts", "insert", "archive + coverage", "update"))
                         + " |")
            report.write(lines, args.out)
    if args.seeds:
        first, second = sweep_seconds(args.seeds)
        lines += ["", f"A sweep of {args.seeds} vmapped \"mqd\" runs of 2D Obstacle, 250 generations (`run_batch`): "
                  f"{first:.1f} s with compiling, {second:.1f} s the second call."]
        report.write(lines, args.out)
    if args.robot_batches:
        lines += ["", *bench_physics.table(args.robot_task, args.robot_batches, args.robot_backends, args.repeats)]
        report.write(lines, args.out)


if __name__ == "__main__":
    main()
