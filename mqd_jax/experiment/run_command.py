"""`mqd run`: one search in a results folder, resumable from its checkpoint, with metrics, repertoire and a plot.

This module parses the flags and prints; what may be done to the folder, and each refusal, is its `RunFolder`'s
(`mqd_jax.experiment.run_folder`). `--resume` takes the saved config and seed, refusing flags that contradict them.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import numpy as np

from mqd_jax.core.config import Config
from mqd_jax.core.state import State
from mqd_jax.experiment import checkpoint, folders, manifest
from mqd_jax.experiment import progress as progress_lib
from mqd_jax.experiment.flags import RUN_DEFAULTS, SEEDS, config_from_flags, flag_given, is_seed
from mqd_jax.experiment.messages import count_of, say_removed
from mqd_jax.experiment.run_folder import RunFolder, upgraded_identity


def _resumed(args: argparse.Namespace, folder: RunFolder) -> tuple[Config, int]:
    """The config and seed of the run saved in `folder` (its manifest, else its checkpoint): what `--resume`
    continues. Flags given must agree with them: refused (ValueError) otherwise, naming each."""
    hint = folder.resume_command()
    saved = manifest.identity(args.out)
    if not (isinstance(saved, dict) and isinstance(saved.get("config"), dict) and is_seed(saved.get("seed"))):
        try:
            saved = {"config": checkpoint.read(folder.checkpoint)["config"], "seed": args.seed or 0}
        except ValueError as e:
            raise ValueError(f"--resume: {e}; nothing in {args.out!r} says which run it continues") from None
    saved = upgraded_identity(saved)
    try:
        cfg = Config.from_dict(saved["config"])
    except (TypeError, ValueError) as e:
        raise ValueError(f"--resume: the config saved in {args.out!r} is invalid ({e}); run afresh in another "
                         "folder") from None
    if flag_given(args, "--preset"):
        flags = config_from_flags(args, defaults=RUN_DEFAULTS)
    else:
        given = {f.name: getattr(args, f.name) for f in dataclasses.fields(Config)
                 if f.name != "algorithm_options" and getattr(args, f.name, None) is not None}
        options = {**cfg.to_dict()["algorithm_options"], **dict(args.algorithm_options)}
        try:
            flags = Config.from_dict({**cfg.to_dict(), **given, "algorithm_options": options})
        except (TypeError, ValueError) as e:
            raise ValueError(f"--resume continues the run saved in {args.out!r} with its own config, which the flags "
                             f"given contradict ({e}); leave them out: `{hint}`") from None
    differ = folders.differences({**cfg.to_dict(), "seed": saved["seed"]},
                         {**flags.to_dict(), "seed": saved["seed"] if args.seed is None else args.seed})
    if differ:
        raise ValueError(f"--resume continues the run saved in {args.out!r} with its own config and seed, which the "
                         f"flags given contradict ({differ}); leave them out: `{hint}`")
    return cfg, saved["seed"]


def run(args: argparse.Namespace) -> None:
    if args.seed is not None and not is_seed(args.seed):
        raise ValueError(f"--seed {args.seed} is invalid: expected an int from 0 to {SEEDS - 1} (PRNGKey(seed): "
                         "larger seeds would share keys)")
    folder = RunFolder(args.out)
    folder.check_request(args.resume, args.overwrite)
    watched = [progress_lib.Progress()]  # the run's progress, once it has one: its `done` generations are saved
    args.interrupted = lambda: folder.interrupted(watched[0].done)
    with folders.lock(args.out) as leftovers:
        say_removed(leftovers, "left by an interrupted writer")
        if args.resume:
            folder.check_resumable()
            cfg, seed = _resumed(args, folder)
        else:
            cfg, seed = config_from_flags(args, defaults=RUN_DEFAULTS), args.seed or 0
        key = jax.random.PRNGKey(seed)
        args.task_now = cfg.task_name
        progress = progress_lib.for_output("", cfg.max_generations, cfg, args.cache_folder, args.cache)
        saved = folder.progress()
        for paths, why in folder.claim(cfg, seed, args.resume, args.overwrite, saved):
            say_removed(paths, why)

        def start(state: State, metrics: dict[str, np.ndarray]) -> None:
            if metrics:
                print(f"resuming at generation {int(state.generation)} of {cfg.max_generations} from "
                      f"{folder.checkpoint}")
            watched[0] = progress

        began = time.perf_counter()
        try:
            state, metrics = checkpoint.run_with_checkpoints(key, cfg, folder.checkpoint, every=args.chunk,
                                                             resume=args.resume, on_start=start, progress=progress)
        except checkpoint.Refused as e:
            raise folder.cannot_continue(e, saved) from e
        meta, written = folder.write(cfg, seed, key, state, metrics)
        print(f"done: coverage {metrics['coverage'][-1]:.3f} ({meta['coverage_measured']}), "
              f"QD-score {metrics['qd_score'][-1]:.2f}, max quality {metrics['max_quality'][-1]:.3f}, "
              f"mean quality {metrics['mean_quality'][-1]:.3f}, {count_of(int(state.repertoire.count), 'skill')}, "
              f"{int(metrics['num_evaluations'][-1])} evaluations, "
              f"{time.perf_counter() - began:.1f} s (compilation included); wrote " + ", ".join(written))
