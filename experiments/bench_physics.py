"""Env-steps per second of a generation's rollouts on each physics backend, next to raw rollouts.

    python experiments/bench_physics.py [--task push_cube] [--populations 100 1024 4096]
        [--backends mujoco mjx warp] [--repeats 3] [--out results/bench_physics.md]

For one generation's worth of random actions (uniform in the task's bounds) at
each batch size: raw `mujoco.rollout` on the same MjModel and control arrays
(one MjData per CPU thread; the controls computed beforehand; the rows the C backend
simulates, those with reachable via-points and a motion that fits), the task's C
MuJoCo backend end to end (jitted `evaluate`: IK, trajectories, the callback,
the behaviors) and the IK and trajectories alone; for "mjx" and "warp" the
backend end to end, and for "warp" also raw MuJoCo Warp through MJX (a jitted,
vmapped `lax.scan` of `mjx.step` on the same controls). Median of `--repeats`
calls after one warm-up call; compile time is the warm-up call's excess over
the median. The device is named in the header (C MuJoCo always runs on the
host's cores). On a CPU, MJX compiles for minutes and MuJoCo Warp runs on
Warp's CPU device: give small `--populations` there.
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

from mqd_jax.core import registry


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


def _raw_mjx(task, ctrl: np.ndarray) -> Callable[[], object]:
    """Raw rollouts through the task's MJX rollout (MJX-JAX or MuJoCo Warp): controls given, no IK."""
    ctrl = jnp.asarray(ctrl, jnp.float32)
    run = jax.jit(task._rollout)
    return lambda: run(ctrl, jnp.ones(ctrl.shape[0], bool))


def table(task_name: str, populations: list[int], backends: list[str], repeats: int) -> list[str]:
    """The markdown table of env-steps per second of `task_name`'s backends at each batch size."""
    c_task = registry.make(task_name, backend="mujoco")
    low, high = jnp.asarray(c_task.action_low), jnp.asarray(c_task.action_high)
    horizon = c_task.horizon
    c = c_task._rollout  # the backend's MjModel, start state, control layout and per-thread MjData
    tasks = {b: registry.make(task_name, backend=b) for b in backends if b != "mujoco"}
    rows: list[tuple[str, int, float, float]] = []
    raw: dict[int, float] = {}
    simulated: dict[int, int] = {}
    for pop in populations:
        a = jax.random.uniform(jax.random.PRNGKey(0), (pop, len(low)), minval=low, maxval=high)
        plan = jax.jit(c_task.plan)(a)
        ctrl = np.asarray(plan.ctrl, np.float64)
        # The C backend simulates only the rows with reachable via-points and a motion that fits; raw
        # mujoco.rollout is timed on those same rows, so both do the same physics.
        rows_run = np.flatnonzero(np.asarray(plan.reached & plan.fits))
        simulated[pop] = len(rows_run)
        raw[pop], _ = _time(lambda ctrl=ctrl[rows_run]: rollout.rollout(
            c.model, c.datas, c.initial_state[None], ctrl), repeats)
        rows.append(("raw mujoco.rollout (controls given), host cores", pop, raw[pop], 0.0))
        if "mujoco" in backends:
            evaluate = jax.jit(c_task.evaluate)
            rows.append(("C MuJoCo backend, end to end", pop,
                         *_time(lambda a=a, f=evaluate: f(a, None), repeats)))
            plan_fn = jax.jit(c_task.plan)
            rows.append(("  of which IK and trajectories", pop, *_time(lambda a=a, f=plan_fn: f(a), repeats)))
        if "warp" in tasks:
            rows.append(("raw MuJoCo Warp through MJX (controls given)", pop,
                         *_time(_raw_mjx(tasks["warp"], ctrl), repeats)))
        for backend, task in tasks.items():
            evaluate = jax.jit(task.evaluate)
            name = {"mjx": "MJX-JAX backend, end to end", "warp": "MuJoCo Warp backend, end to end"}[backend]
            rows.append((name, pop, *_time(lambda a=a, f=evaluate: f(a, None), repeats)))
    lines = [f"{task_name}, horizon {horizon} steps, random actions; {report.machine()}; "
             f"JAX device: {jax.devices()[0].device_kind}.", "",
             "Env-steps count the rows the C backend simulates (" + ", ".join(
                 f"{simulated[n]} of {n}" for n in populations) + "; MJX and Warp simulate every row).", "",
             "| rollouts | batch | s per generation | env-steps / s | vs raw mujoco.rollout (same batch) | compile s |",
             "|---|---|---|---|---|---|"]
    for name, n, s, compile_s in rows:
        rate = simulated[n] * horizon / s
        # Steps per second mean nothing for the IK alone.
        cells = " | " if name.startswith("  of which") else f"{rate:,.0f} | {raw[n] / s:.2f}"
        lines.append(f"| {name} | {n} | {s:.3f} | {cells} | {compile_s:.1f} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="push_cube")
    parser.add_argument("--populations", type=int, nargs="+", default=[100, 1024, 4096])
    parser.add_argument("--backends", nargs="+", default=["mujoco", "mjx", "warp"], choices=["mujoco", "mjx", "warp"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="results/bench_physics.md")
    args = parser.parse_args()
    report.write(table(args.task, args.populations, args.backends, args.repeats), args.out)


if __name__ == "__main__":
    main()
