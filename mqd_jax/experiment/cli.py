"""The `mqd` command line: `run` one search, `sweep` seeds, `adapt` a sweep's skills, `plot` a results folder.

    mqd run   [--preset paper-2d] [--<config-field> VALUE ...] [--seed 0] [--chunk 25] [--resume] [--out DIR]
    mqd sweep [--tasks ...] [--algorithms mqd mqd-paper qd random] [--seeds N] [--<config-field> VALUE ...] [--out DIR]
    mqd adapt DIR [--tasks ...] [--goals 1000]
    mqd plot  DIR
    mqd render DIR [--index N | --goal X Y] [--out FILE.gif]

`run` and `sweep` print a progress line per chunk of generations and a final
summary; every Config field has a flag (`--t-dist 0.03`, `--population 50`) and
a preset's options are `--algorithm-option NAME=VALUE` (`-O pool_factor=16`). A
results folder belongs to one config (`mqd_jax.experiment.folders`): another config is
refused unless `--overwrite`, and one command at a time writes it. Compiled
programs are kept in a persistent cache (`compilation_cache`), so a second
start of the same config skips compilation.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import dataclasses
import difflib
import glob
import json
import logging
import math
import os
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

from mqd_jax import adaptation
from mqd_jax.core import algorithms, registry
from mqd_jax.core.config import Config
from mqd_jax.core.run import State, check_size, get_task
from mqd_jax.experiment import checkpoint, folders, interrupts, migrations, plots, results, shell, sweep
from mqd_jax.experiment import progress as progress_lib
from mqd_jax.experiment.provenance import provenance
from mqd_jax.version import __version__

# Table II's columns, for `--preset`.
COLUMNS = {"paper-2d": Config.paper_2d, "paper-robot": Config.paper_robot}
# Short flags kept from the first versions of the CLI.
_ALIASES = {"max_generations": ["--generations"], "population_size": ["--population"]}
_PER_TASK = ("task", "algorithm")  # `sweep` takes these as lists
SWEPT = ("mqd", "mqd-paper", "qd", "random")  # a bare `mqd sweep`'s algorithms
RUN_FILES = ("metrics.json", "repertoire.npz", "run.png", "checkpoint.msgpack")
SEEDS = 2**32  # a run's key is PRNGKey(seed): seeds 0 .. 2**32 - 1 give distinct keys
_RUN_DEFAULTS = {"max_generations": 100}  # the main job is a short run
CACHE_ENV = "MQD_JAX_CACHE_DIR"
TRACEBACK_ENV = "MQD_TRACEBACK"  # set: an unexpected error shows its traceback instead of one line


def _writable(folder: str) -> bool:
    """Whether files can be made in `folder` (created if missing)."""
    try:
        os.makedirs(folder, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            return True
    except OSError:
        return False


def compilation_cache(enabled: bool) -> tuple[str | None, str]:
    """Turns on JAX's persistent compilation cache; returns its folder (None if off) and what the progress line
    says of it.

    The folder: $MQD_JAX_CACHE_DIR, else $XDG_CACHE_HOME/mqd-jax (default
    ~/.cache/mqd-jax). A cache folder the user gave JAX (JAX_COMPILATION_CACHE_DIR)
    is kept. `--no-cache` or MQD_JAX_CACHE_DIR=off turn it off; a folder that
    cannot be written leaves it off, and says so.
    """
    folder = os.environ.get(CACHE_ENV)
    if not enabled:
        return None, "no compilation cache (--no-cache)"
    if folder in ("0", "off", ""):
        return None, f"no compilation cache ({CACHE_ENV}={folder})"
    if jax.config.jax_compilation_cache_dir:
        folder = jax.config.jax_compilation_cache_dir
        if not _writable(folder):
            return None, (f"no compilation cache: JAX's cache folder {folder} (JAX_COMPILATION_CACHE_DIR) cannot be "
                          "written")
        return folder, f"kept in {folder} for later starts (JAX's own cache folder)"
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    folder = folder or os.path.join(base, "mqd-jax")
    if not _writable(folder):
        return None, f"no compilation cache: {folder} cannot be written (set {CACHE_ENV} to a writable folder)"
    jax.config.update("jax_compilation_cache_dir", folder)
    # Every program, however small or fast to compile: a run compiles several.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder, f"kept in {folder} for later starts"


def _task_names() -> str:
    return ", ".join(registry.registered_tasks()) + ", or a plugin package.module:factory"


def _option(text: str) -> tuple[str, Any]:
    """argparse type: NAME=VALUE, the value as a Python literal (8, 0.5, True, 'parent'; a bare word is a str)."""
    name, sep, value = text.partition("=")
    if not (sep and name.strip()):
        raise argparse.ArgumentTypeError(f"{text!r} is invalid: expected NAME=VALUE (pool_factor=16)")
    try:
        parsed = ast.literal_eval(value.strip())
    except (ValueError, SyntaxError):
        parsed = value.strip()
    return name.strip(), parsed


def _presets_help() -> str:
    """Each preset's options with their defaults (the epilog of `mqd run --help`)."""
    lines = ["algorithm options (--algorithm-option NAME=VALUE; defaults: Table II's 2D column):"]
    for name in algorithms.names():
        taken = algorithms.options(name)
        lines.append(f"  {name}: " + (", ".join(f"{o}={d!r}" for o, d in taken.items()) or "none"))
    return "\n".join(lines)


def _default_text(name: str, defaults: dict[str, Any], preset: str) -> str:
    """The value the flag of the Config field `name` takes when not given, in words, under `preset`."""
    if preset in COLUMNS:
        text = repr(getattr(COLUMNS[preset](**defaults), name))
    else:
        flat, robot = (getattr(column(**defaults), name) for column in (Config.paper_2d, Config.paper_robot))
        text = repr(flat) if flat == robot else f"{flat!r}, {robot!r} for the robot tasks"
    if name == "t_dist":
        text += ", or the task's own where it declares one (Task.default_t_dist)"
    return text


def _add_config_flags(parser: argparse.ArgumentParser, skip: tuple[str, ...] = (), preset: str = "auto",
                      defaults: dict | None = None) -> None:
    """One flag per Config field (`--t-dist 0.03`, `--population 50`) and `--algorithm-option NAME=VALUE`; unset
    flags keep the preset's value (`auto`: Table II's column for the task), after `defaults`.

    The help of each flag shows the value it takes when not given.
    """
    defaults = defaults or {}
    parser.add_argument("--preset", choices=[*sorted(COLUMNS), "auto"], default=preset,
                        help="Table II's column the unset flags take: paper-2d, paper-robot, auto: paper-robot for the "
                             "robot tasks, else paper-2d" + "".join(f"; --{n.replace('_', '-')} {v!r} unless given"
                                                                   for n, v in defaults.items()) +
                             " (default: %(default)s)")
    specific = {"task": f"the task: {_task_names()}", "algorithm": f"one of {', '.join(algorithms.names())}"}
    for field in dataclasses.fields(Config):
        if field.name in skip or field.name == "algorithm_options":
            continue
        flags = ["--" + field.name.replace("_", "-"), *_ALIASES.get(field.name, [])]
        default = _default_text(field.name, defaults, preset)
        text = f"{specific.get(field.name, 'Config.' + field.name)} (default: {default})"
        parser.add_argument(*flags, dest=field.name, type=type(field.default), default=None, help=text)
    parser.add_argument("--algorithm-option", "-O", dest="algorithm_options", type=_option, nargs="+",
                        action="extend", default=[], metavar="NAME=VALUE",
                        help="an option of the algorithm (repeatable): see the list below; Table II's column sets "
                             "the model's (hidden_size 64 with paper-robot)")


def _config(args: argparse.Namespace, defaults: dict | None = None, **fixed: str) -> Config:
    """The config the flags give: preset (auto: paper-robot for the robot tasks), then `defaults`, flags, `fixed`.

    In a sweep (several algorithms), each algorithm takes the options it has; an option none of them has is
    refused (`_sweep`)."""
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(Config)
             if f.name != "algorithm_options" and getattr(args, f.name, None) is not None}
    given.update(fixed)
    options = dict(args.algorithm_options)
    algorithm = given.get("algorithm", Config.algorithm)
    if "algorithm" in fixed:  # a sweep's: only the options this algorithm takes
        options = {o: v for o, v in options.items() if o in algorithms.options(algorithm)}
    settings = {**(defaults or {}), **given, "algorithm_options": options}
    if args.preset == "auto":
        return Config.paper(settings.pop("task", Config.task), **settings)
    return COLUMNS[args.preset](**settings)


def _positive(text: str) -> int:
    """argparse type: an int >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} is invalid: expected an int >= 1")
    return value


def _say_removed(paths: list[str], why: str) -> None:
    """Says which files were removed, and which set aside (`folders.discard`: damaged files, kept as `.damaged`)."""
    aside = [p for p in paths if ".damaged" in os.path.basename(p)]
    gone = [p for p in paths if p not in aside]
    if gone:
        print(f"{why}: removed {', '.join(os.path.basename(p) for p in gone)}")
    if aside:
        print(f"{why}: set aside (damaged, never deleted) as {', '.join(os.path.basename(p) for p in aside)}")


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
        folders.read_json(path, "")
    elif path.endswith(".npz"):
        folders.read_npz(path, "")


def _given(args: argparse.Namespace, flag: str) -> bool:
    """Whether the command line named `flag` (`--preset`, `--seed`)."""
    return any(a == flag or a.startswith(flag + "=") for a in args.argv)


def _resumed(args: argparse.Namespace, path: str) -> tuple[Config, int]:
    """The config and seed of the run saved in `args.out` (its manifest, else its checkpoint): what `--resume`
    continues. Flags given must agree with them: refused (ValueError) otherwise, naming each."""
    hint = shell.command("mqd", "run", "--resume", ("--out", args.out))
    saved = folders.identity(args.out)
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
    if _given(args, "--preset"):
        flags = _config(args, defaults=_RUN_DEFAULTS)
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


def is_seed(seed: Any) -> bool:
    """Whether `seed` is a seed of `mqd run`: an int from 0 to SEEDS - 1."""
    return isinstance(seed, int) and not isinstance(seed, bool) and 0 <= seed < SEEDS


def _run(args: argparse.Namespace) -> None:
    if args.seed is not None and not is_seed(args.seed):
        raise ValueError(f"--seed {args.seed} is invalid: expected an int from 0 to {SEEDS - 1} (PRNGKey(seed): "
                         "larger seeds would share keys)")
    if args.resume and args.overwrite:
        raise ValueError("--resume and --overwrite together: --resume continues the run in the folder, --overwrite "
                         "starts it afresh; give one")
    path = os.path.join(args.out, "checkpoint.msgpack")
    resume = shell.command("mqd", "run", "--resume", ("--out", args.out))
    watched = [progress_lib.Progress()]  # the run's progress, once it has one: its `done` generations are saved

    def interrupted() -> str:
        if watched[0].done:
            return f"interrupted at generation {watched[0].done}; `{resume}` continues from there"
        kept = os.path.lexists(path)
        return ("interrupted before a generation was saved; " +
                (f"the checkpoint already in {args.out!r} is kept as it was" if kept else "nothing was saved"))

    args.interrupted = interrupted
    with folders.lock(args.out) as leftovers:
        _say_removed(leftovers, "left by an interrupted writer")
        if args.resume and not folders.lexists(path):
            raise ValueError(f"--resume: {args.out!r} holds no checkpoint; run without --resume to start")
        if args.resume:
            cfg, seed = _resumed(args, path)
        else:
            cfg, seed = _config(args, defaults=_RUN_DEFAULTS), args.seed or 0
        key = jax.random.PRNGKey(seed)
        args.task_now = cfg.task_name
        progress = progress_lib.for_output("", cfg.max_generations, cfg, args.cache_folder, args.cache)
        saved = _progress_of(path) if folders.is_file(path) else None
        stake = f"; its checkpoint holds {saved[0]} of {saved[1]} generations" if saved else ""
        _say_removed(folders.claim(args.out, "run", {"config": cfg.to_dict(), "seed": seed}, RUN_FILES,
                                   args.overwrite, upgrade=_upgraded_identity, check=_check_file, at_stake=stake),
                     "--overwrite")
        if folders.is_file(path) and not args.resume:
            if not args.overwrite and saved and saved[0] >= cfg.max_generations:
                raise ValueError(f"{args.out!r} holds this run, finished ({cfg.max_generations} generations): its "
                                 "results are there; --overwrite runs it again (deleting them)")
            if not args.overwrite:
                what = f"at generation {saved[0]} of {saved[1]}" if saved else "that is damaged"
                fate = f"deleting those {saved[0]} generations" if saved else "setting the damaged one aside"
                raise ValueError(f"{args.out!r} holds a checkpoint of this run {what}: `{resume}` continues it; "
                                 f"--overwrite starts afresh, {fate}")
            ours = [n for n in folders.written(args.out) if n in RUN_FILES]
            _say_removed(folders.discard(args.out, ours, _check_file), "--overwrite (starting afresh)")

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
                "coverage_measured": results.coverage_measure(cfg, metrics["coverage"][-1]),
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
              f"mean quality {metrics['mean_quality'][-1]:.3f}, {_count(n, 'skill')}, "
              f"{int(metrics['num_evaluations'][-1])} evaluations, "
              f"{time.perf_counter() - began:.1f} s (compilation included); wrote "
              + ", ".join(os.path.join(args.out, f) for f in [*written, folders.MANIFEST]))


def _distinct_file_names(tasks: list[str]) -> None:
    """Refuses (ValueError) two task names that map to one results file name (`pp:sub.f` and `pp.sub:f`)."""
    by_file: dict[str, str] = {}
    for task in tasks:
        other = by_file.setdefault(results.file_name(task), task)
        if other != task:
            raise ValueError(f"--tasks {other} {task}: both map to the file names {results.file_name(task)}_*, so "
                             "one batch would overwrite the other; sweep them into separate folders (--out)")


def _sweep(args: argparse.Namespace) -> None:
    args.tasks, args.algorithms = list(dict.fromkeys(args.tasks)), list(dict.fromkeys(args.algorithms))
    _distinct_file_names(args.tasks)
    taken = {o for a in args.algorithms for o in algorithms.options(a)}
    untaken = [o for o, _ in args.algorithm_options if o not in taken]
    if untaken:
        raise ValueError(f"--algorithm-option {untaken[0]}: none of the algorithms {', '.join(args.algorithms)} "
                         f"takes it (mqd run --help lists each one's options)")
    configs = [_config(args, task=t, algorithm=a) for t in args.tasks for a in args.algorithms]
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
        kept = (f"the {_count(where[2], 'finished batch')} in {args.out!r} are kept" if where[2] else
                "no batch had finished")
        if where[1] is not None and where[1].done:
            return (f"{text} at generation {where[1].done} of {where[1].total}: its checkpoint keeps them, and the "
                    f"same command continues this batch from generation {where[1].done}; {kept}")
        return f"{text}; {kept}" + (", and the same command continues from there" if where[2] else "")

    args.interrupted = interrupted
    with folders.lock(args.out) as leftovers:
        _say_removed(leftovers, "left by an interrupted writer")
        _say_removed(folders.claim(args.out, "sweep", {}, results.files(), args.overwrite), "--overwrite")
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
        _say_removed(results.remove_batches(list(differ)), "--overwrite")
        _say_removed(results.remove_batches(list(stale)), "stale (another implementation)")
        if clash:  # the tables and figures describe removed runs
            _say_removed(results.remove_derived(args.out), "made of the replaced batches")
        found = [(stem, saved) for stem, saved in found if stem not in clash]
        where[2] = len(found)
        planned = {results.stem(args.out, cfg): (cfg, keys) for cfg, keys in batches}
        for stem, e in damaged.items():
            if stem not in planned:
                print(f"warning: {e}")
            elif _loads(args.out, stem + results.PART, *planned[stem]):  # killed while it wrote the batch's files
                print(f"{e}\nits batch is finished from its checkpoint {os.path.basename(stem + results.PART)}")
            else:
                kept = folders.set_aside(results.batch_files(stem))
                print(f"{e}\nits batch is run again; its files are kept as {', '.join(kept)}")
        folders.plan(args.out, [{"task": cfg.task_name, "algorithm": cfg.algorithm, "seeds": len(keys)}
                                for cfg, keys in batches])
        for cfg, keys in batches:
            label = f"{cfg.task} {cfg.algorithm}, {len(keys)} seeds: "
            part = results.stem(args.out, cfg) + results.PART
            if results.is_done(found, args.out, cfg, keys):
                print(f"{label}already in {args.out!r}, skipped")
                _say_removed(folders.remove_written(args.out, [glob.escape(os.path.basename(part))]), "finished")
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
        _plot(args.out)


def _loads(out: str, part: str, cfg: Config, keys: np.ndarray) -> bool:
    """Whether the batch checkpoint `part` (mqd-jax's, by the manifest of `out`) loads as a batch of `cfg` and
    `keys`: a sound part, which a sweep continues (or finishes) and never sets aside."""
    if not (folders.is_file(part) and os.path.basename(part) in folders.written(out)):
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
    if not folders.is_file(part) or os.path.basename(part) not in folders.written(args.out):
        return None, args.chunk
    try:
        payload = checkpoint.read(part)
        chunk = payload.get("chunk")
        if not (isinstance(chunk, int) and chunk >= 1):
            raise checkpoint.Refused(part, "it records no chunk size")
    except ValueError as e:
        print(f"{e}\nthe batch starts afresh; its checkpoint is set aside as "
              f"{', '.join(folders.set_aside([part]))}")
        return None, args.chunk
    try:
        states, metrics = checkpoint.load(part, cfg, keys, payload)
    except checkpoint.Refused as e:
        if not args.overwrite:
            raise ValueError(f"{e}. Pass --overwrite to run the batch afresh (it deletes that checkpoint), or "
                             "write to another folder") from None
        _say_removed(folders.discard(args.out, [os.path.basename(part)]), "--overwrite")
        return None, args.chunk
    done = int(np.asarray(states.generation)[0])
    if chunk != args.chunk:
        print(f"{progress.label}continues in chunks of {chunk} generations, as it began (--chunk {args.chunk} is "
              "taken by batches that start afresh), so that it ends bit for bit as without the stop")
    print(f"{progress.label}resuming at generation {done} of {cfg.max_generations} from {part}")
    return (states, metrics), chunk


def _adapt(args: argparse.Namespace) -> None:
    path = os.path.join(args.dir, results.ADAPTATION)
    with folders.lock(args.dir, create=False) as leftovers:
        _say_removed(leftovers, "left by an interrupted writer")
        _sweep_folder(args.dir, "adapt")
        try:
            found = results.read_adaptation(args.dir)
        except folders.Damaged as e:
            if args.tasks:
                raise ValueError(f"{e} (it holds the other tasks' results)") from e
            kept = folders.set_aside([e.path])
            print(f"{e}\nwritten anew with every task; the damaged file is kept as {kept[0]}")
            found = {}
        tasks = args.tasks or [t for t, by in results.load_runs(args.dir).items() if "mqd" in by]
        if not tasks:
            raise ValueError(f"{args.dir!r} holds no M-QD runs to adapt: run "
                             f"`{shell.command('mqd', 'sweep', '--algorithms', 'mqd', ('--out', args.dir))}` first")
        steps = progress_lib.Steps("adapt", len(tasks) * len(adaptation.METHODS), "method")
        for task in tasks:
            cfg, keys, states = results.load_states(args.dir, task)
            goals = np.stack([adaptation.reachable_goals(get_task(cfg), args.goals, np.random.default_rng(i))
                              for i in range(len(keys))])
            rollout_keys = jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys)
            methods = {}
            for method in adaptation.METHODS:
                start = time.perf_counter()
                out = jax.device_get(adaptation.adapt_batch(states, goals, rollout_keys, cfg, method,
                                                            args.step_size, args.steps))
                methods[method] = {"error": out.errors.mean(1), "steps": out.steps.mean(1),
                                   "reached": (out.errors < cfg.t_dist).mean(1), "goals": args.goals,
                                   "wall_s": time.perf_counter() - start}
                steps.step(f"{task} {method}: mean error {out.errors.mean():.4f}, mean steps "
                           f"{out.steps.mean():.2f}, {methods[method]['wall_s']:.1f} s", f"{task} {method}")
            found[task] = {"source": results.source(args.dir, task), "config": cfg.to_dict(),
                           "step_size": args.step_size, "steps": args.steps, "keys": keys,
                           "provenance": provenance(), "methods": methods}
            results.remove_derived(args.dir)
            folders.write_json(path, found)
        steps.close()
        _plot(args.dir, show="adaptation.md")


def _sweep_folder(folder: str, command: str) -> None:
    """Refuses (ValueError) a folder that `mqd run` wrote: `command` works on a sweep's folder."""
    if folders.kind(folder) == "run":
        raise ValueError(f"{folder!r} is a folder of `mqd run`: `mqd {command}` takes a folder of `mqd sweep` (a "
                         "run's folder holds its figure, run.png; `mqd render` watches its skills)")


def _plot(out: str, pair: tuple[int, int] | None = None, show: str | None = None) -> None:
    """Tables (markdown) and figures of everything in the results folder `out` (call holding its lock); `pair`:
    the two behavior dimensions (0-based) Figure 2 shows of each task that has them (refused if none has); `show`:
    print only this table (default: every one)."""
    runs = results.load_runs(out)
    dims = {task: get_task(next(iter(by_alg.values())).cfg).behavior_dim for task, by_alg in runs.items()}
    if pair is not None and not any(max(pair) < d for d in dims.values()):  # before anything is written
        plots.projections(max(dims.values()), pair)  # raises, naming the dimensions
    results.remove_derived(out)
    results.write_markdown(results.tables(runs, results.missing(out)), os.path.join(out, "table1.md"),
                           show in (None, "table1.md"))
    for task, by_alg in runs.items():
        plots.figure2(get_task(next(iter(by_alg.values())).cfg), task, by_alg,
                      os.path.join(out, f"fig2_{results.file_name(task)}.png"),
                      pair if pair is not None and max(pair) < dims[task] else None)
    try:
        found, stale = results.adaptation(out)
    except folders.Damaged as e:
        print(f"left out the adaptation results: {e}")
        found, stale = {}, []
    if stale:
        print(f"left out the adaptation results of {', '.join(stale)}: their M-QD runs changed since `mqd adapt`; "
              f"run `mqd adapt {out} --tasks {' '.join(stale)}` again")
    if found:
        results.write_markdown(results.adaptation_table(found), os.path.join(out, "adaptation.md"),
                               show in (None, "adaptation.md"))
        plots.adaptation_figure(found, "error", "behavioral error", os.path.join(out, "fig3_adaptation_error.png"))
        plots.adaptation_figure(found, "steps", "adaptation steps", os.path.join(out, "fig4_adaptation_steps.png"))


def _count(n: int, noun: str) -> str:
    """'1 skill', '3 skills'."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _rounded(values: np.ndarray) -> list[float]:
    """values as Python floats rounded to 3 decimals (float32's binary noise gone: 0.199, not 0.19900000095)."""
    return [round(float(v), 3) for v in np.asarray(values, np.float64)]


def _render(args: argparse.Namespace) -> None:
    """A skill of a `mqd run` folder as an animated GIF: the robot executing it, or a 2D task's behavior path."""
    # Offscreen OpenGL for MuJoCo's renderer unless the user chose a platform (read when mujoco is imported).
    os.environ.setdefault("MUJOCO_GL", "egl")
    if not os.path.isdir(args.dir):
        raise ValueError(f"{args.dir!r} does not exist: give the folder a `mqd run` wrote")
    if folders.kind(args.dir) == "sweep":
        raise ValueError(f"{args.dir!r} is a folder of `mqd sweep`: `mqd render` takes a folder of `mqd run` "
                         f"(`{shell.command('mqd', 'plot', args.dir)}` draws a sweep's repertoires)")
    files = [os.path.join(args.dir, f) for f in ("metrics.json", "repertoire.npz")]
    missing = [f for f in files if not os.path.lexists(f)]
    if missing:
        raise ValueError(f"{missing[0]!r} is missing: {args.dir!r} is not a whole folder of `mqd run` (metrics.json, "
                         "repertoire.npz)")
    repair = (f"the `mqd run` that made it, `{shell.command('mqd', 'run', '--resume', ('--out', args.dir))}`, writes "
              "it again from its checkpoint")
    saved = folders.read_json(files[0], repair)
    if not isinstance(saved.get("config"), dict):
        raise ValueError(f"{args.dir!r} is not a folder of `mqd run` (no config in metrics.json): {repair}")
    try:
        cfg = migrations.config_from(saved["config"])
    except (TypeError, ValueError) as e:
        raise folders.Damaged(files[0], f"holds an invalid config ({e})", repair) from None
    arrays = folders.read_npz(files[1], repair, results.npz_bytes(cfg))
    if not {"actions", "behaviors"} <= set(arrays):
        raise ValueError(f"{args.dir!r} is not a folder of `mqd run` (no actions or behaviors): {repair}")
    actions, behaviors = arrays["actions"], arrays["behaviors"]
    if len(actions) == 0:
        raise ValueError(f"{files[1]!r} holds no skills (the run inserted none): there is nothing to render")
    if args.goal is not None and not all(math.isfinite(g) for g in args.goal):
        raise ValueError(f"--goal {' '.join(map(str, args.goal))} is invalid: expected finite numbers")
    if args.goal is not None and len(args.goal) != behaviors.shape[1]:
        raise ValueError(f"--goal {' '.join(map(str, args.goal))} has {len(args.goal)} numbers: the task's behaviors "
                         f"have {behaviors.shape[1]}")
    if args.goal is not None:
        index = int(np.argmin(np.linalg.norm(behaviors - np.asarray(args.goal), axis=1)))
    elif 0 <= args.index < len(actions):
        index = args.index
    else:
        raise ValueError(f"--index {args.index}: the repertoire holds {_count(len(actions), 'skill')} (0 to "
                         f"{len(actions) - 1})")
    out = args.out or os.path.join(args.dir, f"skill_{index}.gif")
    target = os.path.dirname(out) or "."
    if not out.lower().endswith(".gif") or not os.path.isdir(target):
        raise ValueError(f"--out {out!r} is invalid: expected a new .gif file in an existing folder")
    ours = folders.kind(target) is not None  # a results folder: its lock, and only files its manifest lists
    if not ours and os.path.lexists(out):
        raise ValueError(f"--out {out!r} exists: `mqd render` replaces only a GIF it wrote in a results folder; "
                         "remove it, or give another --out")
    print(f"skill {index}: behavior {_rounded(behaviors[index])}, action {_rounded(actions[index])}")
    with folders.lock(target, create=False) if ours else contextlib.nullcontext():
        if ours and folders.lexists(out) and os.path.basename(out) not in folders.written(target):
            raise ValueError(f"--out {out!r} is not written by mqd-jax there (not in its manifest), so it is not "
                             "replaced: remove it, or give another --out")
        try:
            frames = get_task(cfg).frames(actions[index], args.width, args.height)
        except NotImplementedError as e:
            raise ValueError(str(e)) from e
        except Exception as e:  # MuJoCo's OpenGL context: say how to get one offscreen
            if "gl" not in str(e).lower():
                raise
            raise ValueError(f"cannot render ({type(e).__name__}: {e}); offscreen: set MUJOCO_GL=egl (or osmesa)"
                             ) from e
        plots.write_animation(frames, out)


def _locked_plot(args: argparse.Namespace) -> None:
    pair = None if args.pair is None else (args.pair[0] - 1, args.pair[1] - 1)
    with folders.lock(args.dir, create=False) as leftovers:
        _say_removed(leftovers, "left by an interrupted writer")
        _sweep_folder(args.dir, "plot")
        _plot(args.dir, pair)


def _parser() -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    parser = _Parser(prog="mqd", description="Model-Based Quality-Diversity search in JAX")
    parser.add_argument("--version", action="version", version=f"mqd-jax {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    cache = _Parser(add_help=False)
    cache.add_argument("--no-cache", dest="cache", action="store_false",
                       help=f"do not keep compiled programs in the persistent cache (${CACHE_ENV}, default "
                            "~/.cache/mqd-jax)")
    writes = _Parser(add_help=False)
    writes.add_argument("--overwrite", action="store_true",
                        help="replace results of another config in the folder (otherwise refused); removes only "
                             "files mqd-jax wrote there")

    run = sub.add_parser("run", parents=[cache, writes], help="run one search and write metrics, repertoire and a plot",
                         epilog=_presets_help(), formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_config_flags(run, defaults=_RUN_DEFAULTS)
    run.add_argument("--seed", type=int, default=None,
                     help=f"the run's key is PRNGKey(seed), 0 <= seed < {SEEDS} (default: 0; with --resume, the "
                          "saved run's)")
    run.add_argument("--chunk", type=_positive, default=25,
                     help="generations per chunk: one progress line and one checkpoint each (default: %(default)s)")
    run.add_argument("--resume", action="store_true",
                     help="continue the run saved in OUT from its checkpoint, with its saved config and seed (no other "
                          "flags needed; flags given must agree with them); without it, a checkpoint in OUT is refused")
    run.add_argument("--out", default="results/run", help="results folder (default: %(default)s)")

    sw = sub.add_parser("sweep", parents=[cache, writes],
                        help="seed sweeps (vmapped, sharded over devices): metrics, Table I, Figure 2",
                        epilog=_presets_help() + "\n(each algorithm of a sweep takes the options it has)",
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_config_flags(sw, skip=_PER_TASK)
    sw.add_argument("--tasks", nargs="+", default=list(registry.registered_tasks()), metavar="TASK",
                    help=f"tasks to sweep: {_task_names()} (default: every registered task)")
    sw.add_argument("--algorithms", nargs="+", default=list(SWEPT), choices=algorithms.names(),
                    help=f"default: {' '.join(SWEPT)} (the paper's comparison and this library's M-QD)")
    sw.add_argument("--seeds", type=_positive, default=None,
                    help="default: the paper's, 25 (2D tasks) or 10 (robot tasks)")
    sw.add_argument("--chunk", type=_positive, default=25,
                    help="generations per compiled chunk, one progress line each (default: %(default)s)")
    sw.add_argument("--rerun-stale", action="store_true",
                    help="run again the batches in the folder written by another mqd-jax version or another "
                         "implementation of the task (otherwise refused)")
    sw.add_argument("--out", default="results/sweep",
                    help="results folder; batches already in it (same config and seeds) are skipped "
                         "(default: %(default)s)")

    ad = sub.add_parser("adapt", parents=[cache], help="adapt a sweep's final M-QD repertoires toward random goals")
    ad.add_argument("dir", help="a results folder of `mqd sweep`")
    ad.add_argument("--tasks", nargs="+", default=None, help="default: every task with M-QD runs in DIR")
    ad.add_argument("--goals", type=_positive, default=1000,
                    help="goals per repertoire (default: the paper's %(default)s)")
    ad.add_argument("--step-size", type=float, default=adaptation.STEP_SIZE,
                    help="lambda, the step along the Jacobian's pseudo-inverse (default: Table II's %(default)s)")
    ad.add_argument("--steps", type=int, default=adaptation.STEPS,
                    help="the most steps (rollouts) per goal (default: Table II's %(default)s)")

    pl = sub.add_parser("plot", help="tables and figures of a results folder")
    pl.add_argument("dir", help="a results folder of `mqd sweep` (its tables and figures are written there)")
    pl.add_argument("--pair", type=int, nargs=2, metavar=("I", "J"), default=None,
                    help="Figure 2 shows behaviors I and J (1-based) of each task that has them (default: 1 and 2)")

    rd = sub.add_parser("render", help="watch a skill of a `mqd run` folder: an animated GIF")
    rd.add_argument("dir", help="a results folder of `mqd run`")
    which = rd.add_mutually_exclusive_group()
    which.add_argument("--index", type=int, default=0, help="the skill's row in repertoire.npz (default: 0)")
    which.add_argument("--goal", type=float, nargs="+", metavar="B", default=None,
                       help="the skill whose behavior is nearest to this one (d numbers)")
    rd.add_argument("--out", default=None, help="the GIF to write (default: DIR/skill_<index>.gif)")
    rd.add_argument("--width", type=_positive, default=320, help="the GIF's width in pixels (default: %(default)s)")
    rd.add_argument("--height", type=_positive, default=240, help="the GIF's height in pixels (default: %(default)s)")
    return parser, {"run": run, "sweep": sw, "adapt": ad, "plot": pl, "render": rd}


_COMMANDS: dict[str, Callable[[argparse.Namespace], None]] = {
    "run": _run, "sweep": _sweep, "adapt": _adapt, "plot": _locked_plot, "render": _render}


def _one_line(e: BaseException) -> str:
    """What went wrong, in one line: an OSError's file and reason, else the exception's type and first line."""
    if isinstance(e, OSError) and e.strerror:
        where = " -> ".join(repr(f) for f in (e.filename, e.filename2) if f is not None)
        return f"{where + ': ' if where else ''}{e.strerror}"
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else 'no message'}"


class _Parser(argparse.ArgumentParser):
    """argparse's parser whose errors are one line (with a "did you mean" for a mistyped flag), not the usage."""

    def error(self, message: str) -> Any:
        flags = [o for a in self._actions for o in a.option_strings if o.startswith("--")]
        words = [w for w in message.split() if w.startswith("--")] if "unrecognized" in message else []
        close = difflib.get_close_matches(words[0].split("=")[0], flags, n=1) if words else []
        hint = f"did you mean {close[0]}? " if close else ""
        self.exit(2, f"{self.prog}: error: {message} ({hint}`{self.prog} --help` lists the flags)\n")


class _CallbackFailures(logging.Handler):
    """Keeps, silently, what a task's host callback (`jax.pure_callback`) raised: JAX logs its traceback and then
    fails the program with an error that names neither the task nor the cause; the command says both, in a line."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.raised: BaseException | None = None

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info and record.exc_info[1] is not None:
            self.raised = record.exc_info[1]


@contextlib.contextmanager
def _callbacks_caught() -> Any:
    """Catches the traceback JAX's callback module logs (`_CallbackFailures`) while a command runs, unless
    MQD_TRACEBACK asks for tracebacks."""
    logger, handler = logging.getLogger("jax._src.callback"), _CallbackFailures()
    if os.environ.get(TRACEBACK_ENV):
        yield handler
        return
    propagate = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _format_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                    line: str | None = None) -> str:
    """A warning as one line, `warning: ...` (a `RunWarning` about the run, not the library's source line)."""
    return f"warning: {message}\n"


@contextlib.contextmanager
def _one_line_warnings() -> Any:
    """Warnings formatted by `_format_warning` while a command runs; Python's own formatting afterwards."""
    own, warnings.formatwarning = warnings.formatwarning, _format_warning
    try:
        yield
    finally:
        warnings.formatwarning = own


def _arguments(parser: argparse.ArgumentParser, subparsers: dict[str, argparse.ArgumentParser],
               argv: list[str] | None) -> argparse.Namespace:
    """The command line's arguments, with what every command reads: the cache, and what an interruption says."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # the subcommand's one line, not the top level's
        subparsers[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")
    args.argv = argv
    args.interrupted = lambda: "interrupted"  # run and sweep say where
    args.task_now = None  # the task running (run and sweep set it): what a callback's failure names
    args.cache_folder, args.cache = compilation_cache(getattr(args, "cache", False))
    return args


def _say_interrupted(args: argparse.Namespace | None) -> None:
    """Says where the command was interrupted, in one line, and exits 130."""
    print(f"\n{args.interrupted() if args else 'interrupted while starting; nothing was written'}", file=sys.stderr)
    raise SystemExit(130) from None


def main(argv: list[str] | None = None) -> None:
    """The `mqd` command line in this process: exits (SystemExit) 2 with one line for invalid input or a failure,
    130 with one line on Ctrl-C, wherever it is pressed (`interrupts`)."""
    args = None
    with interrupts.latched(), _callbacks_caught() as callbacks, _one_line_warnings():
        try:
            parser, subparsers = _parser()
            args = _arguments(parser, subparsers, argv)
            _COMMANDS[args.command](args)
            interrupts.check()  # a press whose KeyboardInterrupt was lost after the last chunk
        except ValueError as e:  # invalid configuration or input: one line that says what, no traceback
            print(f"mqd {args.command if args else ''}: error: {e}", file=sys.stderr)
            raise SystemExit(2) from None
        except KeyboardInterrupt:
            _say_interrupted(args)
        except Exception as e:  # a file that cannot be written, a task's own failure: one line too
            if interrupts.pressed():  # an error Ctrl-C caused (an extension's import, a callback): say that
                _say_interrupted(args)
            if os.environ.get(TRACEBACK_ENV) or args is None:
                raise
            where = args.interrupted().replace("interrupted", "stopped", 1)
            what = _one_line(e)
            if callbacks.raised is not None:
                task = f"the task {args.task_now!r}" if args.task_now else "the task"
                what = (f"{task} failed during the run: its host callback (jax.pure_callback) raised "
                        f"{_one_line(callbacks.raised)}")
            print(f"mqd {args.command}: error: {what} ({where}; {TRACEBACK_ENV}=1 shows the traceback)",
                  file=sys.stderr)
            raise SystemExit(2) from None


if __name__ == "__main__":
    main()
