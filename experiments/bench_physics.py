"""Env-steps per second of a generation's rollouts on each physics backend, next to raw `mujoco.rollout`.

    python experiments/bench_physics.py [--task push_cube] [--population 100] [--mjx-populations 100 1024]
                                        [--repeats 3] [--out results/bench_physics.md]

For one generation's worth of random actions (uniform in the task's bounds):
raw `mujoco.rollout` on the same MjModel and the same control arrays (one
MjData per CPU thread; the controls computed beforehand), the task's C MuJoCo
backend end to end (jitted `evaluate`: IK, trajectories, the callback, the
behaviors), the IK and trajectories alone, and the MJX backend end to end at
each `--mjx-populations` (skip with an empty list; slow to compile on a CPU).
Median of `--repeats` calls after one warm-up call; compile time is the warm-up
call's excess over the median.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import report
from mujoco import rollout

from mqd_jax import registry


def _time(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(median seconds of `repeats` calls, first call's excess over it)."""
    start = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    median = statistics.median(times)
    return median, max(first - median, 0.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="push_cube")
    parser.add_argument("--population", type=int, default=100)
    parser.add_argument("--mjx-populations", type=int, nargs="*", default=[100, 1024])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="results/bench_physics.md")
    args = parser.parse_args()
    c_task = registry.make(args.task, backend="mujoco")
    low, high = jnp.asarray(c_task.action_low), jnp.asarray(c_task.action_high)

    def actions(pop: int) -> jax.Array:
        return jax.random.uniform(jax.random.PRNGKey(0), (pop, len(low)), minval=low, maxval=high)

    pop, horizon = args.population, c_task.horizon
    steps = pop * horizon
    a = actions(pop)
    ctrl = np.asarray(jax.jit(c_task.rollout_controls)(a), np.float64)
    c = c_task._rollout  # the backend's MjModel, start state, control layout and per-thread MjData
    rows: list[tuple[str, int, float, float]] = []
    raw_s, _ = _time(lambda: rollout.rollout(c.model, c.datas, c.initial_state[None], ctrl,
                                             control_spec=int(c.control_spec)), args.repeats)
    rows.append(("raw mujoco.rollout (controls given)", pop, raw_s, 0.0))
    evaluate = jax.jit(c_task.evaluate)
    c_s, c_compile = _time(lambda: evaluate(a, None), args.repeats)
    rows.append(("C MuJoCo backend, end to end", pop, c_s, c_compile))
    controls = jax.jit(c_task.controls)
    ik_s, ik_compile = _time(lambda: controls(a), args.repeats)
    rows.append(("  of which IK and trajectories", pop, ik_s, ik_compile))
    if args.mjx_populations:
        mjx_task = registry.make(args.task, backend="mjx")
        mjx_evaluate = jax.jit(mjx_task.evaluate)
        for n in args.mjx_populations:
            b = actions(n)
            s, compile_s = _time(lambda b=b: mjx_evaluate(b, None), args.repeats)
            rows.append(("MJX backend, end to end", n, s, compile_s))
    lines = [f"{args.task}, horizon {horizon} steps, random actions; {report.machine()}.", "",
             "| rollouts | batch | s per generation | env-steps / s | vs raw mujoco.rollout | compile s |",
             "|---|---|---|---|---|---|"]
    for name, n, s, compile_s in rows:
        rate = n * horizon / s
        # Steps per second mean nothing for the IK alone.
        cells = " | " if name.startswith("  of which") else f"{rate:,.0f} | {rate / (steps / raw_s):.2f}"
        lines.append(f"| {name} | {n} | {s:.3f} | {cells} | {compile_s:.1f} |")
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
