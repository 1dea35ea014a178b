"""Side-by-side speed of mqd-jax (QD, M-QD), pyribs and QDax on 2D Obstacle, in one process.

    python experiments/bench_qd.py [--generations 250] [--qdax-generations 10] [--out results/bench_qd.md]
    python experiments/bench_qd.py --only-ratios [--ratio-tasks obstacle2d push_cube] [--out ...]
    python experiments/bench_qd.py --only-batches [--batches 100 1024 4096] [--batch-generations 100] [--out ...]

All run the paper's 2D settings (population 100, K 5, t_dist 0.02) on the same
task: mqd-jax through its jitted `run_mqd`; pyribs (`pip install -e .[bench]`)
through a `ProximityArchive` with local competition and an iso+line emitter,
evaluating with the numpy path of the very same dynamics; QDax 0.5 through an
`UnstructuredRepertoire` (l_value t_dist, capacity as ours) with its
`isoline_variation` and uniform parent selection, evaluating with the JAX path
in one jitted `lax.scan`. QDax runs fewer generations (it is slow), reported
per generation. Also sweeps our repertoire capacity. Writes a markdown table
(ratios are against pyribs, measured in this run).

Then M-QD's cost against QD's where it matters, on each of `--ratio-tasks` (default 2D Obstacle, whose
rollouts are nearly free, and PushCube on C MuJoCo, where a rollout costs far more than the model): one
generation of the default "mqd" and of QD at Table II's settings, from repertoires grown for the task's
Table II generations, timed in turns (`generation_ratio.ms_per_generation`). `--only-ratios` measures
only that (the peers need the `bench` extra).

And the batch sizes a user with many cores picks (`--batches`): whole runs of `--batch-generations` from an
empty archive at each population, pyribs' `ProximityArchive` (as above, unbounded) against our QD and M-QD
(capacity max(4096, batch)), compile excluded, one process, back to back; `--only-batches` measures only that.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
import report
from generation_ratio import ms_per_generation

from mqd_jax import Config, run_mqd
from mqd_jax.core import registry

TASK = "obstacle2d"


def bench_ours(cfg: Config, seed: int = 0) -> dict:
    key = jax.random.PRNGKey(seed)
    start = time.perf_counter()
    jax.block_until_ready(run_mqd(key, cfg))  # compiles (and runs once)
    first_s = time.perf_counter() - start
    start = time.perf_counter()
    state, metrics = jax.block_until_ready(run_mqd(key, cfg))
    run_s = time.perf_counter() - start
    compile_s = first_s - run_s
    return dict(compile_s=compile_s, ms_per_gen=run_s / cfg.max_generations * 1e3,
                evals_per_s=int(metrics["num_evaluations"][-1]) / run_s, size=int(state.repertoire.count),
                coverage=float(metrics["coverage"][-1]), dropped=int(metrics["dropped_full"].sum()))


def bench_pyribs(cfg: Config, seed: int = 0) -> dict:
    from ribs.archives import ProximityArchive
    from ribs.emitters import IsoLineEmitter
    from ribs.schedulers import Scheduler

    task = registry.make(TASK)
    low, high = np.asarray(task.action_low), np.asarray(task.action_high)
    archive = ProximityArchive(solution_dim=task.action_dim, measure_dim=task.behavior_dim, k_neighbors=cfg.k,
                               novelty_threshold=cfg.t_dist, local_competition=True, seed=seed)
    iso, line = cfg.options["iso_sigma"], cfg.options["line_sigma"]
    emitter = IsoLineEmitter(archive, x0=(low + high) / 2, iso_sigma=iso * float(np.mean(high - low)),
                             line_sigma=line, bounds=list(zip(low, high, strict=True)),
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


def bench_qdax(cfg: Config, generations: int, seed: int = 0) -> dict:
    from qdax.core.containers.unstructured_repertoire import UnstructuredRepertoire
    from qdax.core.emitters.mutation_operators import isoline_variation

    task = registry.make(TASK)
    low, high = jnp.asarray(task.action_low), jnp.asarray(task.action_high)
    pop = cfg.population_size

    def run(key: jax.Array) -> tuple[UnstructuredRepertoire, jax.Array]:
        key, k0 = jax.random.split(key)
        x0 = jax.random.uniform(k0, (pop, task.action_dim), minval=low, maxval=high)
        b0, q0, _ = task.evaluate(x0, None)
        rep = UnstructuredRepertoire.init(x0, q0, b0, jnp.float32(cfg.t_dist), cfg.capacity)

        def generation(carry: tuple, _: None) -> tuple:
            rep, key = carry
            key, k1, k2, k3 = jax.random.split(key, 4)
            x1, x2 = rep.select(k1, pop).genotypes, rep.select(k2, pop).genotypes
            iso, line = cfg.options["iso_sigma"], cfg.options["line_sigma"]
            x = isoline_variation(x1, x2, k3, iso * (high - low), line, low, high)
            b, q, _ = task.evaluate(x, None)
            return (rep.add(x, b, q), key), None

        (rep, _), _ = jax.lax.scan(generation, (rep, key), None, length=generations - 1)
        return rep, rep.get_number_genotypes()

    key = jax.random.PRNGKey(seed)
    start = time.perf_counter()
    compiled = jax.jit(run).lower(key).compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    _, size = jax.block_until_ready(compiled(key))
    run_s = time.perf_counter() - start
    return dict(compile_s=compile_s, ms_per_gen=run_s / generations * 1e3, evals_per_s=generations * pop / run_s,
                size=int(size), coverage=float("nan"), dropped=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--generations", type=int, default=250)
    parser.add_argument("--qdax-generations", type=int, default=10, help="0 leaves QDax out")
    parser.add_argument("--capacities", type=int, nargs="*", default=[1024, 4096, 16384])
    parser.add_argument("--ratio-tasks", nargs="*", default=["obstacle2d", "push_cube"])
    parser.add_argument("--only-ratios", action="store_true", help="only M-QD against QD (no peers)")
    parser.add_argument("--batches", type=int, nargs="*", default=[100, 1024, 4096])
    parser.add_argument("--batch-generations", type=int, default=100)
    parser.add_argument("--only-batches", action="store_true", help="only the batch sizes against pyribs")
    parser.add_argument("--out", default="results/bench_qd.md")
    args = parser.parse_args()
    if args.only_batches:
        report.write(batches(args), args.out)
        return
    lines = [f"Machine: {report.machine()}.", ""] if args.only_ratios else peers(args) + batches(args)
    if args.ratio_tasks:
        lines += ["M-QD (\"mqd\", its defaults) against QD, one generation at Table II's settings from repertoires "
                  "grown for the task's Table II generations (C MuJoCo on the robot tasks), fastest of 5 rounds' "
                  "medians of 20 calls:", "", "| task | QD ms / generation | M-QD ms / generation | x QD |",
                  "|---|---|---|---|"]
        for task in args.ratio_tasks:
            ms = ms_per_generation(task, ["mqd"])
            lines.append(f"| {task} | {ms['qd']:.2f} | {ms['mqd']:.2f} | {ms['mqd'] / ms['qd']:.2f} |")
            print(lines[-1], flush=True)
    report.write(lines, args.out)


def batches(args: argparse.Namespace) -> list[str]:
    """Whole runs at each of `args.batches` candidates per generation: pyribs against our QD and M-QD (markdown)."""
    lines = [f"2D Obstacle, whole runs of {args.batch_generations} generations from empty, compile excluded; "
             f"{report.machine()}.", "",
             "| batch | pyribs ms / generation | our QD ms / generation | x pyribs | our M-QD ms / generation "
             "| x pyribs |", "|---|---|---|---|---|---|"]
    for batch in args.batches:
        cfg = Config.paper_2d(task=TASK, algorithm="qd", max_generations=args.batch_generations,
                              population_size=batch, capacity=max(4096, batch), archive_capacity=max(4096, batch))
        bench_pyribs(dataclasses.replace(cfg, max_generations=5))  # pyribs' first calls pay one-time costs
        ribs, qd = bench_pyribs(cfg)["ms_per_gen"], bench_ours(cfg)["ms_per_gen"]
        mqd = bench_ours(dataclasses.replace(cfg, algorithm="mqd"))["ms_per_gen"]
        lines.append(f"| {batch} | {ribs:.2f} | {qd:.2f} | {qd / ribs:.2f} | {mqd:.2f} | {mqd / ribs:.2f} |")
        print(lines[-1], flush=True)
        report.write(lines, args.out)
    return [*lines, ""]


def peers(args: argparse.Namespace) -> list[str]:
    """The side-by-side table of pyribs, QDax and mqd-jax on 2D Obstacle (markdown lines)."""
    cfg = Config.paper_2d(task=TASK, algorithm="qd", max_generations=args.generations)

    rows = [("pyribs ProximityArchive + iso-line", bench_pyribs(cfg))]
    rows.append((f"mqd-jax QD (capacity {cfg.capacity})", bench_ours(cfg)))
    mqd = bench_ours(dataclasses.replace(cfg, algorithm="mqd"))
    rows.append((f"mqd-jax M-QD ({mqd['ms_per_gen'] / rows[1][1]['ms_per_gen']:.2f}x our QD)", mqd))
    if args.qdax_generations:
        rows.append((f"QDax UnstructuredRepertoire + iso-line ({args.qdax_generations} generations)",
                     bench_qdax(cfg, args.qdax_generations)))
    for cap in args.capacities:
        rows.append((f"mqd-jax QD, capacity {cap}", bench_ours(Config.paper_2d(
            task=TASK, max_generations=args.generations, capacity=cap, archive_capacity=cap))))
    base = rows[0][1]["ms_per_gen"]
    archive_only = rows[0][1]["archive_ms"]

    machine = report.machine()
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
              "pyribs' ask/tell alone.", ""]
    return lines


if __name__ == "__main__":
    main()
