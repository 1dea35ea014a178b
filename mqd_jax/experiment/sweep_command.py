"""`mqd sweep`: seed sweeps of tasks and algorithms into one results folder, batch by batch, each resumable from
its checkpoint (`<task>_<alg>.part.msgpack`). This module parses the flags, prints and runs; what may be done to
the folder, and each refusal, is its `SweepFolder`'s (`mqd_jax.experiment.sweep_folder`)."""

from __future__ import annotations

import argparse
import glob
import os
import time
from typing import Any

import jax
import numpy as np

from mqd_jax.core import algorithms
from mqd_jax.core.state import check_size, get_task
from mqd_jax.experiment import checkpoint, folders, manifest, results, sweep
from mqd_jax.experiment import progress as progress_lib
from mqd_jax.experiment.flags import config_from_flags
from mqd_jax.experiment.folder_commands import tabulate
from mqd_jax.experiment.messages import say_removed
from mqd_jax.experiment.sweep_folder import SweepFolder


def _distinct_file_names(tasks: list[str]) -> None:
    """Refuses (ValueError) two task names that map to one results file name (`pp:sub.f` and `pp.sub:f`)."""
    by_file: dict[str, str] = {}
    for task in tasks:
        other = by_file.setdefault(results.file_name(task), task)
        if other != task:
            raise ValueError(f"--tasks {other} {task}: both map to the file names {results.file_name(task)}_*, so "
                             "one batch would overwrite the other; sweep them into separate folders (--out)")


def sweep_seeds(args: argparse.Namespace) -> None:
    args.tasks, args.algorithms = list(dict.fromkeys(args.tasks)), list(dict.fromkeys(args.algorithms))
    _distinct_file_names(args.tasks)
    taken = {o for a in args.algorithms for o in algorithms.options(a)}
    untaken = [o for o, _ in args.algorithm_options if o not in taken]
    if untaken:
        raise ValueError(f"--algorithm-option {untaken[0]}: none of the algorithms {', '.join(args.algorithms)} "
                         f"takes it (mqd run --help lists each one's options)")
    configs = [config_from_flags(args, task=t, algorithm=a) for t in args.tasks for a in args.algorithms]
    for cfg in configs:  # every size before any key is made: a huge --seeds is refused, not run out of memory
        seeds = args.seeds or get_task(cfg).paper_seeds
        try:
            check_size(cfg, -(-seeds // jax.device_count()))
        except ValueError as e:
            raise ValueError(f"{cfg.task} {cfg.algorithm}, {seeds} seeds: {e}, or give fewer --seeds") from None
    batches = [(cfg, np.asarray(sweep.seed_keys(args.seeds or get_task(cfg).paper_seeds))) for cfg in configs]
    folder = SweepFolder(args.out)
    where: list[Any] = ["before the first batch", None]  # where, and the running batch's progress

    def interrupted() -> str:
        running = where[1]
        return folder.interrupted(where[0], running.done if running else 0, running.total if running else 0)

    args.interrupted = interrupted
    with folders.lock(args.out) as leftovers:
        say_removed(leftovers, "left by an interrupted writer")
        found, said, lines = folder.claim(batches, args.overwrite, args.rerun_stale)
        for paths, why in said:
            say_removed(paths, why)
        for line in lines:
            print(line)
        manifest.plan(args.out, [{"task": cfg.task_name, "algorithm": cfg.algorithm, "seeds": len(keys)}
                                 for cfg, keys in batches])
        for cfg, keys in batches:
            label = f"{cfg.task} {cfg.algorithm}, {len(keys)} seeds: "
            part = results.stem(args.out, cfg) + results.PART
            if results.is_done(found, args.out, cfg, keys):
                print(f"{label}already in {args.out!r}, skipped")
                say_removed(manifest.remove_written(args.out, [glob.escape(os.path.basename(part))]), "finished")
                continue
            progress = progress_lib.for_output(label, cfg.max_generations, cfg, args.cache_folder, args.cache)
            where[:] = [f"in {label.rstrip(': ')}", progress]
            args.task_now = cfg.task_name
            begun, chunk, said, lines = folder.resumed_batch(part, cfg, keys, args.chunk, args.overwrite,
                                                             progress.label)
            for paths, why in said:
                say_removed(paths, why)
            for line in lines:
                print(line)
            start = time.perf_counter()
            if begun is not None and int(np.asarray(begun[0].generation)[0]) >= cfg.max_generations:
                states, metrics = begun  # every generation ran: only its files are left to write
            else:
                states, metrics = sweep.run_batch(
                    cfg, keys, chunk=chunk, start=begun, progress=progress,
                    on_state=lambda s, m, cfg=cfg, keys=keys, part=part, chunk=chunk: checkpoint.save(
                        part, s, m, cfg, keys, chunk=chunk))
            wall = time.perf_counter() - start
            print(f"{label}done: coverage {metrics['coverage'][:, -1].mean():.3f} +- "
                  f"{metrics['coverage'][:, -1].std():.3f}, {metrics['num_evaluations'][:, -1].mean():.0f} "
                  f"evaluations per run, {wall:.1f} s (compilation included) on {jax.device_count()} device(s)",
                  flush=True)
            results.save_runs(args.out, cfg, keys, states, metrics, wall)
            folder.finished += 1
        where[:] = ["while tabulating", None]
        tabulate(args.out)
