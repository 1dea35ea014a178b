"""The `mqd` command line: `run` one search, `sweep` seeds, `adapt` a sweep's skills, `plot` a results folder.

    mqd run   [--preset paper-2d] [--<config-field> VALUE ...] [--seed 0] [--chunk 25] [--resume] [--out DIR]
    mqd sweep [--tasks ...] [--algorithms mqd qd random] [--seeds N] [--<config-field> VALUE ...] [--out DIR]
    mqd adapt DIR [--tasks ...] [--goals 1000]
    mqd plot  DIR

`run` and `sweep` print a progress line per chunk of generations and a final
summary; every Config field has a flag (`--t-nov 0.05`, `--budgeted`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
import warnings
from collections.abc import Callable

import jax
import numpy as np

import envs
from mqd_jax import adaptation, checkpoint, plots, results, sweep
from mqd_jax.config import ALGORITHMS, Config
from mqd_jax.run import get_task

PRESETS = {"paper-2d": Config.paper_2d, "paper-robot": Config.paper_robot}
# Short flags kept from the first versions of the CLI.
_ALIASES = {"max_generations": ["--generations"], "population_size": ["--population"]}
_PER_TASK = ("task", "algorithm")  # `sweep` takes these as lists


def _add_config_flags(parser: argparse.ArgumentParser, skip: tuple[str, ...] = (), preset: str = "paper-2d") -> None:
    """One flag per Config field (`--t-nov 0.05`, `--budgeted/--no-budgeted`); unset flags keep the preset's value."""
    choices = sorted(PRESETS) + ([] if preset in PRESETS else [preset])
    parser.add_argument("--preset", choices=choices, default=preset)
    for field in dataclasses.fields(Config):
        if field.name in skip:
            continue
        flags = ["--" + field.name.replace("_", "-"), *_ALIASES.get(field.name, [])]
        if isinstance(field.default, bool):
            parser.add_argument(*flags, dest=field.name, action=argparse.BooleanOptionalAction, default=None)
        else:
            parser.add_argument(*flags, dest=field.name, type=type(field.default), default=None,
                                help=f"Config.{field.name} (default: the preset's, {field.default!r} in Config)")


def _config(args: argparse.Namespace, defaults: dict | None = None, **fixed: str) -> Config:
    """The config the flags give: preset (auto: paper-robot for the robot tasks), then `defaults`, flags, `fixed`."""
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(Config)
             if getattr(args, f.name, None) is not None}
    given.update(fixed)
    preset = Config.paper if args.preset == "auto" else PRESETS[args.preset]
    return preset(**{**(defaults or {}), **given})


def _progress(label: str, total: int) -> Callable[[int, dict[str, np.ndarray]], None]:
    """A progress printer for chunks of metrics [generations] (one run) or [runs, generations] (a sweep)."""
    start, discarded = time.perf_counter(), [0]

    def show(done: int, m: dict[str, np.ndarray]) -> None:
        cov = np.atleast_2d(m["coverage"])[:, -1]
        spread = f" +- {cov.std():.3f}" if len(cov) > 1 else ""
        discarded[0] += int(np.atleast_2d(m["discarded"]).sum(1).mean())  # per run
        mean = lambda name: np.atleast_2d(m[name])[:, -1].mean()  # noqa: E731
        print(f"{label}generation {done:4d}/{total}  coverage {cov.mean():.3f}{spread}  "
              f"size {mean('repertoire_size'):6.0f}  evaluations {mean('num_evaluations'):7.0f}  "
              f"discarded {discarded[0]:6d}  {done / (time.perf_counter() - start):.1f} gen/s", flush=True)

    return show


def _warn_dropped(metrics: dict[str, np.ndarray], cfg: Config) -> None:
    dropped = int(metrics["dropped_full"].sum())
    if dropped:
        warnings.warn(f"{cfg.task} {cfg.algorithm}: {dropped} new niches did not fit: raise --capacity above "
                      f"{cfg.capacity}", stacklevel=1)


def _run(args: argparse.Namespace) -> None:
    # The main job is a short run: 100 generations unless told otherwise.
    cfg = _config(args, defaults={"max_generations": 100})
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "checkpoint.msgpack")
    if os.path.exists(path) and not args.resume:
        print(f"starting afresh; pass --resume to continue the checkpoint in {path}")
    start = time.perf_counter()
    show = _progress("", cfg.max_generations)
    state, metrics = checkpoint.run_with_checkpoints(
        jax.random.PRNGKey(args.seed), cfg, path, every=max(1, args.chunk), resume=args.resume,
        on_chunk=lambda s, m: show(int(s.generation), m))
    _warn_dropped(metrics, cfg)
    print(f"done: coverage {metrics['coverage'][-1]:.3f}, mean quality {metrics['mean_quality'][-1]:.3f}, "
          f"{int(state.repertoire.count)} skills, {int(metrics['num_evaluations'][-1])} evaluations, "
          f"{time.perf_counter() - start:.1f} s (compilation included)")
    results.write_json(os.path.join(args.out, "metrics.json"), metrics)
    n = int(state.repertoire.count)
    rep = jax.device_get(state.repertoire)
    np.savez(os.path.join(args.out, "repertoire.npz"), actions=rep.actions[:n], behaviors=rep.behaviors[:n],
             qualities=rep.qualities[:n])
    plots.run_figure(get_task(cfg), metrics, rep.behaviors[:n], os.path.join(args.out, "run.png"))


def _sweep(args: argparse.Namespace) -> None:
    configs = [_config(args, task=t, algorithm=a) for t in args.tasks for a in args.algorithms]
    for cfg in configs:
        seeds = args.seeds if args.seeds is not None else 10 if cfg.task in envs.ROBOT_TASKS else 25
        keys = np.asarray(sweep.seed_keys(seeds))
        label = f"{cfg.task} {cfg.algorithm}, {seeds} seeds: "
        if results.is_done(args.out, cfg, keys):
            print(f"{label}already in {args.out}, skipped")
            continue
        start = time.perf_counter()
        states, metrics = sweep.run_batch(cfg, keys, chunk=args.chunk, on_chunk=_progress(label, cfg.max_generations))
        wall = time.perf_counter() - start
        _warn_dropped(metrics, cfg)
        print(f"{label}done: coverage {metrics['coverage'][:, -1].mean():.3f} +- {metrics['coverage'][:, -1].std():.3f}"
              f", {metrics['num_evaluations'][:, -1].mean():.0f} evaluations per run, {wall:.1f} s "
              f"(compilation included) on {jax.device_count()} device(s)", flush=True)
        results.save_runs(args.out, cfg, keys, states, metrics, wall)
    _plot(args.out)


def _adapt(args: argparse.Namespace) -> None:
    path = os.path.join(args.dir, "adaptation.json")
    found: dict = {}
    if os.path.exists(path):
        with open(path) as f:
            found = json.load(f)
    tasks = args.tasks or [t for t, by in results.load_runs(args.dir).items() if "mqd" in by]
    for task in tasks:
        cfg, keys, states = results.load_states(args.dir, task)
        goals = np.stack([adaptation.reachable_goals(get_task(cfg), args.goals, np.random.default_rng(i))
                          for i in range(len(keys))])
        rollout_keys = jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys)
        found[task] = {}
        for method in adaptation.METHODS:
            start = time.perf_counter()
            out = jax.device_get(adaptation.adapt_batch(states, goals, rollout_keys, cfg, method))
            found[task][method] = {"error": out.errors.mean(1), "steps": out.steps.mean(1),
                                   "reached": (out.errors < cfg.t_dist).mean(1), "goals": args.goals,
                                   "wall_s": time.perf_counter() - start}
            print(f"{task} {method}: mean error {out.errors.mean():.4f}, mean steps {out.steps.mean():.2f}, "
                  f"{found[task][method]['wall_s']:.1f} s", flush=True)
        results.write_json(path, found)
    _plot(args.dir)


def _plot(out: str) -> None:
    """Tables (markdown) and figures of everything in the results folder `out`."""
    runs = results.load_runs(out)
    results.write_markdown(results.tables(runs), os.path.join(out, "table1.md"))
    for task, by_alg in runs.items():
        plots.figure2(get_task(next(iter(by_alg.values())).cfg), task, by_alg, os.path.join(out, f"fig2_{task}.png"))
    path = os.path.join(out, "adaptation.json")
    if os.path.exists(path):
        with open(path) as f:
            found = json.load(f)
        found = {task: found[task] for task in sorted(found, key=results.task_order)}
        results.write_markdown(results.adaptation_table(found), os.path.join(out, "adaptation.md"))
        plots.adaptation_figure(found, "error", "behavioral error", os.path.join(out, "fig3_adaptation_error.png"))
        plots.adaptation_figure(found, "steps", "adaptation steps", os.path.join(out, "fig4_adaptation_steps.png"))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="mqd", description="Model-Based Quality-Diversity search in JAX")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run one search and write metrics, repertoire and a plot")
    _add_config_flags(run)
    run.add_argument("--seed", type=int, default=0)
    run.add_argument("--chunk", type=int, default=25,
                     help="generations per compiled chunk: one progress line and one checkpoint each")
    run.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.msgpack")
    run.add_argument("--out", default="results/run")

    sw = sub.add_parser("sweep", help="seed sweeps (vmapped, sharded over devices): metrics, Table I, Figure 2")
    _add_config_flags(sw, skip=_PER_TASK, preset="auto")
    sw.add_argument("--tasks", nargs="+", default=list(envs.registered_tasks()), metavar="TASK")
    sw.add_argument("--algorithms", nargs="+", default=list(ALGORITHMS), choices=ALGORITHMS)
    sw.add_argument("--seeds", type=int, default=None, help="default: the paper's, 25 (2D tasks) or 10 (robot tasks)")
    sw.add_argument("--chunk", type=int, default=25, help="generations per compiled chunk (one progress line each)")
    sw.add_argument("--out", default="results/sweep",
                    help="results folder; batches already in it (same config and seeds) are skipped")

    ad = sub.add_parser("adapt", help="adapt a sweep's final M-QD repertoires toward random reachable goals")
    ad.add_argument("dir", help="a results folder of `mqd sweep`")
    ad.add_argument("--tasks", nargs="+", default=None, help="default: every task with M-QD runs in DIR")
    ad.add_argument("--goals", type=int, default=1000, help="goals per repertoire (the paper's 1000)")

    pl = sub.add_parser("plot", help="tables and figures of a results folder")
    pl.add_argument("dir")
    args = parser.parse_args(argv)
    try:
        if args.command == "run":
            _run(args)
        elif args.command == "sweep":
            _sweep(args)
        elif args.command == "adapt":
            if args.goals < 1:
                raise ValueError(f"--goals {args.goals} is invalid: expected an int >= 1")
            _adapt(args)
        else:
            _plot(args.dir)
    except ValueError as e:  # invalid configuration or input: say what, not a traceback
        parser.error(str(e))


if __name__ == "__main__":
    main()
