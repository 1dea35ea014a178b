"""`mqd run`: one search in a results folder, resumable from its checkpoint, with metrics, repertoire and a plot.

The folder belongs to one run (config and seed, `folders.claim`); another is refused unless `--overwrite`; a
checkpoint of this run is refused without `--resume` (naming the generations `--overwrite` would delete), and
`--resume` takes the saved config and seed, refusing flags that contradict them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from typing import Any

import jax
import numpy as np

from mqd_jax.core.config import Config
from mqd_jax.core.state import State, get_task
from mqd_jax.experiment import checkpoint, files, folders, manifest, messages, migrations, plots, results, tables
from mqd_jax.experiment import progress as progress_lib
from mqd_jax.experiment.flags import RUN_DEFAULTS, SEEDS, config_from_flags, flag_given, is_seed
from mqd_jax.experiment.messages import count_of, say_removed
from mqd_jax.experiment.provenance import provenance

RUN_FILES = ("metrics.json", "repertoire.npz", "run.png", "checkpoint.msgpack")


def _upgraded_identity(identity: dict[str, Any]) -> dict[str, Any]:
    """A run folder's identity saved by an earlier version, its config in today's form."""
    if not isinstance(identity.get("config"), dict):
        return identity
    return {**identity, "config": migrations.upgraded(identity["config"])}


def _progress_of(path: str) -> tuple[int, int] | None:
    """(generations done, of how many) of the checkpoint `path`; None where there is none or it is damaged."""
    try:
        payload = checkpoint.read(path)
        return int(np.asarray(payload["state"]["generation"]).reshape(-1)[0]), \
            int(payload["config"]["max_generations"])
    except (ValueError, KeyError, TypeError, IndexError):
        return None


def _check_file(path: str) -> None:
    """Raises ValueError if the results file `path` is damaged (what `--overwrite` sets aside rather than deletes):
    a checkpoint that `checkpoint.read` refuses, a JSON or npz file that fails its checksum."""
    if path.endswith(".msgpack"):
        checkpoint.read(path)
    elif path.endswith(".json"):
        files.read_json(path, "")
    elif path.endswith(".npz"):
        files.read_npz(path, "")


def _resumed(args: argparse.Namespace, path: str) -> tuple[Config, int]:
    """The config and seed of the run saved in `args.out` (its manifest, else its checkpoint): what `--resume`
    continues. Flags given must agree with them: refused (ValueError) otherwise, naming each."""
    hint = messages.command("mqd", "run", "--resume", ("--out", args.out))
    saved = manifest.identity(args.out)
    if not (isinstance(saved, dict) and isinstance(saved.get("config"), dict) and is_seed(saved.get("seed"))):
        try:
            saved = {"config": checkpoint.read(path)["config"], "seed": args.seed or 0}
        except ValueError as e:
            raise ValueError(f"--resume: {e}; nothing in {args.out!r} says which run it continues") from None
    saved = _upgraded_identity(saved)
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
    if args.resume and args.overwrite:
        raise ValueError("--resume and --overwrite together: --resume continues the run in the folder, --overwrite "
                         "starts it afresh; give one")
    path = os.path.join(args.out, "checkpoint.msgpack")
    resume = messages.command("mqd", "run", "--resume", ("--out", args.out))
    watched = [progress_lib.Progress()]  # the run's progress, once it has one: its `done` generations are saved

    def interrupted() -> str:
        if watched[0].done:
            return f"interrupted at generation {watched[0].done}; `{resume}` continues from there"
        kept = os.path.lexists(path)
        return ("interrupted before a generation was saved; " +
                (f"the checkpoint already in {args.out!r} is kept as it was" if kept else "nothing was saved"))

    args.interrupted = interrupted
    with folders.lock(args.out) as leftovers:
        say_removed(leftovers, "left by an interrupted writer")
        if args.resume and not files.lexists(path):
            raise ValueError(f"--resume: {args.out!r} holds no checkpoint; run without --resume to start")
        if args.resume:
            cfg, seed = _resumed(args, path)
        else:
            cfg, seed = config_from_flags(args, defaults=RUN_DEFAULTS), args.seed or 0
        key = jax.random.PRNGKey(seed)
        args.task_now = cfg.task_name
        progress = progress_lib.for_output("", cfg.max_generations, cfg, args.cache_folder, args.cache)
        saved = _progress_of(path) if files.is_file(path) else None
        stake = f"; its checkpoint holds {saved[0]} of {saved[1]} generations" if saved else ""
        say_removed(folders.claim(args.out, "run", {"config": cfg.to_dict(), "seed": seed}, RUN_FILES,
                                   args.overwrite, upgrade=_upgraded_identity, check=_check_file, at_stake=stake),
                     "--overwrite")
        if files.is_file(path) and not args.resume:
            if not args.overwrite and saved and saved[0] >= cfg.max_generations:
                raise ValueError(f"{args.out!r} holds this run, finished ({cfg.max_generations} generations): its "
                                 "results are there; --overwrite runs it again (deleting them)")
            if not args.overwrite:
                what = f"at generation {saved[0]} of {saved[1]}" if saved else "that is damaged"
                fate = f"deleting those {saved[0]} generations" if saved else "setting the damaged one aside"
                raise ValueError(f"{args.out!r} holds a checkpoint of this run {what}: `{resume}` continues it; "
                                 f"--overwrite starts afresh, {fate}")
            ours = [n for n in manifest.written(args.out) if n in RUN_FILES]
            say_removed(folders.discard(args.out, ours, _check_file), "--overwrite (starting afresh)")

        def start(state: State, metrics: dict[str, np.ndarray]) -> None:
            if metrics:
                print(f"resuming at generation {int(state.generation)} of {cfg.max_generations} from {path}")
            watched[0] = progress

        began = time.perf_counter()
        try:
            state, metrics = checkpoint.run_with_checkpoints(key, cfg, path, every=args.chunk, resume=args.resume,
                                                             on_start=start, progress=progress)
        except checkpoint.Refused as e:
            fresh = "The run's own command with --overwrite (in place of --resume)"
            try:
                _check_file(path)
                fate = f"deletes it ({saved[0]} of {saved[1]} generations)" if saved else "deletes it"
            except ValueError:
                fate = "sets it aside as checkpoint.msgpack.damaged (never deletes it)"
            raise ValueError(f"{e}; the run cannot continue from it. {fresh} starts it afresh and {fate}") from e
        meta = {"config": cfg.to_dict(), "seed": seed, "key": np.asarray(key).tolist(),
                "coverage_measured": tables.coverage_measure(cfg, metrics["coverage"][-1]),
                "implementation": results.implementation(cfg), "provenance": provenance()}
        folders.write_json(os.path.join(args.out, "metrics.json"), {**meta, "metrics": metrics})
        n = int(state.repertoire.count)
        rep = jax.device_get(state.repertoire)
        description = json.dumps(meta)
        folders.write_npz(os.path.join(args.out, "repertoire.npz"), actions=rep.actions[:n],
                          behaviors=rep.behaviors[:n], qualities=rep.qualities[:n], meta=np.asarray(description))
        title = f"{cfg.task}, {cfg.algorithm}, seed {seed}, {cfg.max_generations} generations"
        figure = plots.run_figure(get_task(cfg), metrics, rep.behaviors[:n], os.path.join(args.out, "run.png"),
                                  title, description, rep.qualities[:n])
        written = [f for f in RUN_FILES if f != "run.png" or figure]
        print(f"done: coverage {metrics['coverage'][-1]:.3f} ({meta['coverage_measured']}), "
              f"QD-score {metrics['qd_score'][-1]:.2f}, max quality {metrics['max_quality'][-1]:.3f}, "
              f"mean quality {metrics['mean_quality'][-1]:.3f}, {count_of(n, 'skill')}, "
              f"{int(metrics['num_evaluations'][-1])} evaluations, "
              f"{time.perf_counter() - began:.1f} s (compilation included); wrote "
              + ", ".join(os.path.join(args.out, f) for f in [*written, manifest.MANIFEST]))

