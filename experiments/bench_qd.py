"""Side-by-side speed of mqd-jax QD and pyribs on 2D Obstacle, in one process.

    python experiments/bench_qd.py [--generations 250] [--out results/bench_qd.md]

Both run the paper's 2D settings (population 100, K 5, t_dist 0.02) on the same
task: mqd-jax through its jitted `run_mqd`, pyribs (`pip install -e .[bench]`)
through a `ProximityArchive` with local competition and an iso+line emitter,
evaluating with the numpy path of the very same dynamics. Also sweeps our
repertoire capacity. Writes a markdown table (ratios are against pyribs,
measured in this run).
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax
import numpy as np

import envs
from mqd_jax import Config, run_mqd

TASK = "obstacle2d"


def bench_ours(cfg: Config, seed: int = 0) -> dict:
    key = jax.random.PRNGKey(seed)
    start = time.perf_counter()
    compiled = run_mqd.lower(key, cfg).compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    state, metrics = compiled(key)
    jax.block_until_ready(metrics)
    run_s = time.perf_counter() - start
    return dict(compile_s=compile_s, ms_per_gen=run_s / cfg.max_generations * 1e3,
                evals_per_s=int(metrics["num_evaluations"][-1]) / run_s, size=int(state.repertoire.count),
                coverage=float(metrics["coverage"][-1]), dropped=int(metrics["dropped_full"].sum()))


def bench_pyribs(cfg: Config, seed: int = 0) -> dict:
    from ribs.archives import ProximityArchive
    from ribs.emitters import IsoLineEmitter
    from ribs.schedulers import Scheduler

    task = envs.make(TASK)
    low, high = np.asarray(task.action_low), np.asarray(task.action_high)
    archive = ProximityArchive(solution_dim=task.action_dim, measure_dim=task.behavior_dim, k_neighbors=cfg.k,
                               novelty_threshold=cfg.t_dist, local_competition=True, seed=seed)
    emitter = IsoLineEmitter(archive, x0=(low + high) / 2, iso_sigma=cfg.iso_sigma * float(np.mean(high - low)),
                             line_sigma=cfg.line_sigma, bounds=list(zip(low, high, strict=True)),
                             batch_size=cfg.population_size, seed=seed)
    scheduler = Scheduler(archive, [emitter])
    eval_s = 0.0
    start = time.perf_counter()
    for _ in range(cfg.max_generations):
        actions = scheduler.ask()
        t = time.perf_counter()
        behaviors, qualities, _ = task.evaluate(actions.astype(np.float32))
        eval_s += time.perf_counter() - t
        scheduler.tell(qualities, behaviors)
    run_s = time.perf_counter() - start
    print(f"pyribs: {(run_s - eval_s) / cfg.max_generations * 1e3:.2f} ms/generation in ask/tell, "
          f"{eval_s / cfg.max_generations * 1e3:.2f} ms in numpy rollouts")
    return dict(compile_s=0.0, ms_per_gen=run_s / cfg.max_generations * 1e3,
                archive_ms=(run_s - eval_s) / cfg.max_generations * 1e3,
                evals_per_s=cfg.max_generations * cfg.population_size / run_s, size=len(archive),
                coverage=float("nan"), dropped=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--generations", type=int, default=250)
    parser.add_argument("--capacities", type=int, nargs="*", default=[1024, 4096, 16384])
    parser.add_argument("--out", default="results/bench_qd.md")
    args = parser.parse_args()
    cfg = Config.paper_2d(task=TASK, algorithm="qd", max_generations=args.generations)

    rows = [("pyribs ProximityArchive + iso-line", bench_pyribs(cfg))]
    rows.append((f"mqd-jax QD (capacity {cfg.capacity})", bench_ours(cfg)))
    for cap in args.capacities:
        rows.append((f"mqd-jax QD, capacity {cap}", bench_ours(Config.paper_2d(
            task=TASK, max_generations=args.generations, capacity=cap, archive_capacity=cap))))
    base = rows[0][1]["ms_per_gen"]
    archive_only = rows[0][1]["archive_ms"]

    machine = f"{platform.machine()}, {os.cpu_count()} CPU cores, jax {jax.__version__} on {jax.default_backend()}"
    lines = [
        f"2D Obstacle, population {cfg.population_size}, {args.generations} generations, K {cfg.k}, "
        f"t_dist {cfg.t_dist}; {machine}.", "",
        "| run | compile s | ms / generation | ratio to pyribs | evaluations / s | final size | coverage "
        "| dropped (full) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows:
        lines.append(f"| {name} | {r['compile_s']:.1f} | {r['ms_per_gen']:.2f} | {r['ms_per_gen'] / base:.2f} "
                     f"| {r['evals_per_s']:.0f} | {r['size']} | {r['coverage']:.3f} | {r['dropped']} |")
    lines += ["", f"pyribs spent {archive_only:.2f} ms / generation in its archive and emitter (ask/tell) and the "
              f"rest in the numpy rollouts; our whole generation is {rows[1][1]['ms_per_gen'] / archive_only:.2f}x "
              "pyribs' ask/tell alone."]
    table = "\n".join(lines)
    print(table)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        f.write(table + "\n")


if __name__ == "__main__":
    main()
