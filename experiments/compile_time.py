"""Where compiling a run's program goes: the whole chunk and each stage of a generation, traced and compiled alone.

    python experiments/compile_time.py [--task push_cube] [--algorithms qd mqd] [--out results/compile_time.md]
    python experiments/compile_time.py --algorithms mqd mqd:steering_share=0   # an algorithm with options
    PYTHONPATH=OLD_CHECKOUT:experiments python experiments/compile_time.py ...   # the same, older code (0.13 on)

For each algorithm (Table II's column of the task, `Config.paper`), the program `mqd run` compiles (a chunk
of generations, `lax.scan` of one generation: `checkpoint.compile_chunk`'s) and, alone, the stages of a
generation (`ask`: the emitter's proposal; `rollouts`: the task's `evaluate`; `insert`: the repertoire's
insertion; `update`: the emitter's update, M-QD's training). Each: seconds to trace and lower, seconds for
XLA to compile, and the lowered program's size (StableHLO operations). No compilation cache.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from typing import Any

import jax
import report
from accelerator_timings import generation_parts, inserted

import mqd_jax
from mqd_jax import Config, init
from mqd_jax.core.run import _update_emitter, ask, run_generations
from mqd_jax.core.state import get_task


def timed(fn: Callable[..., Any], *args: Any, static: tuple[int, ...] = ()) -> tuple[float, float, int]:
    """(seconds to trace and lower, seconds to compile, StableHLO operations) of jit(fn)(*args)."""
    start = time.perf_counter()
    lowered = jax.jit(fn, static_argnums=static).lower(*args)
    traced = time.perf_counter() - start
    text = lowered.as_text()
    start = time.perf_counter()
    lowered.compile()
    return traced, time.perf_counter() - start, sum(" = " in line for line in text.splitlines())


def rows(task: str, algorithm: str) -> dict[str, tuple[float, float, int]]:
    """The programs' times of `algorithm`: a preset's name, or "name:option=value,..." (values as JSON)."""
    name, _, given = algorithm.partition(":")
    options = {k: json.loads(v) for k, v in (item.split("=", 1) for item in given.split(","))} if given else {}
    cfg = Config.paper(task, algorithm=name, algorithm_options=options)
    params = cfg.params()
    state = init(jax.random.PRNGKey(0), cfg)
    found = {"run chunk": timed(lambda s, p: run_generations(s, cfg, p, 10), state, params)}
    t = get_task(cfg)
    candidates, b, q, usable, kept, rep, _, evaluated = generation_parts(state, cfg, params)
    found["ask"] = timed(lambda s, p: ask(s, cfg, p), state, params)
    found["rollouts"] = timed(lambda a, k, m: t.evaluate_with_auxiliary(a, k, m), candidates.actions, candidates.key,
                              candidates.rollout)
    # Every array an argument: one closed over would be a constant, which XLA may fold at compile time.
    found["insert"] = timed(lambda s, a, b, q, u, p, f: inserted(s.repertoire, a, b, q, u, p, cfg, f),
                            state, candidates.actions, b, q, usable, params, kept)
    found["update"] = timed(lambda s, c, e, r, p: _update_emitter(jax.random.PRNGKey(1), s, c, e, r, cfg, p),
                            state, candidates, evaluated, rep, params)
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="push_cube")
    parser.add_argument("--algorithms", nargs="+", default=["qd", "mqd"])
    parser.add_argument("--out", default="results/compile_time.md")
    args = parser.parse_args()
    jax.config.update("jax_enable_compilation_cache", False)
    lines = [f"mqd-jax {mqd_jax.__version__}; {report.machine()}; {args.task}, Table II's column; no compilation "
             "cache.", "", "| algorithm | program | trace + lower (s) | compile (s) | StableHLO ops |",
             "|---|---|---|---|---|"]
    for algorithm in args.algorithms:
        for name, (traced, compiled, ops) in rows(args.task, algorithm).items():
            lines.append(f"| {algorithm} | {name} | {traced:.1f} | {compiled:.1f} | {ops:,} |")
            report.write(lines, args.out)


if __name__ == "__main__":
    main()
