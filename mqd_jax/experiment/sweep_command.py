"""`mqd sweep`: seed sweeps of tasks and algorithms into one results folder, batch by batch, each resumable from
its checkpoint (`<task>_<alg>.part.msgpack`); batches already there are skipped, conflicting ones refused before
anything runs, a batch killed while its files were written finished from its checkpoint."""

from __future__ import annotations

import argparse
import glob
import os
import time
from typing import Any

import jax
import numpy as np

from mqd_jax.core import algorithms
from mqd_jax.core.config import Config
from mqd_jax.core.state import State, check_size, get_task
from mqd_jax.experiment import checkpoint, files, folders, manifest, results, sweep
from mqd_jax.experiment import progress as progress_lib
from mqd_jax.experiment.flags import config_from_flags
from mqd_jax.experiment.folder_commands import tabulate
from mqd_jax.experiment.messages import count_of, say_removed


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
    where: list[Any] = ["before the first batch", None, 0]  # where, the running batch's progress, batches in the folder

    def interrupted() -> str:
        text = f"interrupted {where[0]}"
        kept = (f"the {count_of(where[2], 'finished batch')} in {args.out!r} are kept" if where[2] else
                "no batch had finished")
        if where[1] is not None and where[1].done:
            return (f"{text} at generation {where[1].done} of {where[1].total}: its checkpoint keeps them, and the "
                    f"same command continues this batch from generation {where[1].done}; {kept}")
        return f"{text}; {kept}" + (", and the same command continues from there" if where[2] else "")

    args.interrupted = interrupted
    with folders.lock(args.out) as leftovers:
        say_removed(leftovers, "left by an interrupted writer")
        say_removed(folders.claim(args.out, "sweep", {}, results.patterns(), args.overwrite), "--overwrite")
        # Every conflict is found before anything runs, not after hours of other batches: one read of the folder.
        found, damaged = results.scan(args.out)
        clash = results.conflicts(found, batches)
        differ = {s: c for s, c in clash.items() if not c.stale}
        stale = {s: c for s, c in clash.items() if c.stale}
        if differ and not args.overwrite:
            raise ValueError(f"{args.out!r} refused: {results.describe(differ)}. Pass --overwrite to replace those "
                             "batches, or write to another folder")
        if stale and not (args.rerun_stale or args.overwrite):
            raise ValueError(f"{args.out!r} refused: {results.describe(stale)}. Pass --rerun-stale to run those "
                             "batches again with this implementation, or write to another folder")
        say_removed(results.remove_batches(list(differ)), "--overwrite")
        say_removed(results.remove_batches(list(stale)), "stale (another implementation)")
        if clash:  # the tables and figures describe removed runs
            say_removed(results.remove_derived(args.out), "made of the replaced batches")
        found = [(stem, saved) for stem, saved in found if stem not in clash]
        where[2] = len(found)
        planned = {results.stem(args.out, cfg): (cfg, keys) for cfg, keys in batches}
        for stem, e in damaged.items():
            if stem not in planned:
                print(f"warning: {e}")
            elif _loads(args.out, stem + results.PART, *planned[stem]):  # killed while it wrote the batch's files
                print(f"{e}\nits batch is finished from its checkpoint {os.path.basename(stem + results.PART)}")
            else:
                kept = files.set_aside(results.batch_files(stem))
                print(f"{e}\nits batch is run again; its files are kept as {', '.join(kept)}")
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
            where[:2] = [f"in {label.rstrip(': ')}", progress]
            args.task_now = cfg.task_name
            begun, chunk = _resumed_batch(args, part, cfg, keys, progress)
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
            where[2] += 1
        where[:2] = ["while tabulating", None]
        tabulate(args.out)


def _loads(out: str, part: str, cfg: Config, keys: np.ndarray) -> bool:
    """Whether the batch checkpoint `part` (mqd-jax's, by the manifest of `out`) loads as a batch of `cfg` and
    `keys`: a sound part, which a sweep continues (or finishes) and never sets aside."""
    if not (files.is_file(part) and os.path.basename(part) in manifest.written(out)):
        return False
    try:
        checkpoint.load(part, cfg, keys)
    except ValueError:
        return False
    return True


def _resumed_batch(args: argparse.Namespace, part: str, cfg: Config, keys: np.ndarray,
                   progress: progress_lib.Lines) -> tuple[tuple[State, dict[str, np.ndarray]] | None, int]:
    """Where a sweep's batch starts: from its checkpoint `part` (an interrupted batch: its states, metrics and
    chunk size, so it ends bit for bit as without the stop), or afresh (None, --chunk). A damaged checkpoint is set
    aside; one of another config or keys is refused unless --overwrite, which deletes it."""
    if not files.is_file(part) or os.path.basename(part) not in manifest.written(args.out):
        return None, args.chunk
    try:
        payload = checkpoint.read(part)
        chunk = payload.get("chunk")
        if not (isinstance(chunk, int) and chunk >= 1):
            raise checkpoint.Refused(part, "it records no chunk size")
    except ValueError as e:
        print(f"{e}\nthe batch starts afresh; its checkpoint is set aside as "
              f"{', '.join(files.set_aside([part]))}")
        return None, args.chunk
    try:
        states, metrics = checkpoint.load(part, cfg, keys, payload)
    except checkpoint.Refused as e:
        if not args.overwrite:
            raise ValueError(f"{e}. Pass --overwrite to run the batch afresh (it deletes that checkpoint), or "
                             "write to another folder") from None
        say_removed(folders.discard(args.out, [os.path.basename(part)]), "--overwrite")
        return None, args.chunk
    done = int(np.asarray(states.generation)[0])
    if chunk != args.chunk:
        print(f"{progress.label}continues in chunks of {chunk} generations, as it began (--chunk {args.chunk} is "
              "taken by batches that start afresh), so that it ends bit for bit as without the stop")
    print(f"{progress.label}resuming at generation {done} of {cfg.max_generations} from {part}")
    return (states, metrics), chunk

