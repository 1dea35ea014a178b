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

This module parses and dispatches; each command is its own module (`run_command`, `sweep_command`,
`folder_commands`), and the flags that make a config are `flags`.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import logging
import os
import sys
import tempfile
import warnings
from collections.abc import Callable
from typing import Any

import jax

from mqd_jax import adaptation
from mqd_jax.core import algorithms, registry
from mqd_jax.experiment import folder_commands, interrupts, run_command, sweep_command
from mqd_jax.experiment.flags import (
    PER_TASK,
    RUN_DEFAULTS,
    SEEDS,
    SWEPT,
    add_config_flags,
    positive_int,
    presets_help,
    task_names,
)
from mqd_jax.version import __version__

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
                         epilog=presets_help(), formatter_class=argparse.RawDescriptionHelpFormatter)
    add_config_flags(run, defaults=RUN_DEFAULTS)
    run.add_argument("--seed", type=int, default=None,
                     help=f"the run's key is PRNGKey(seed), 0 <= seed < {SEEDS} (default: 0; with --resume, the "
                          "saved run's)")
    run.add_argument("--chunk", type=positive_int, default=25,
                     help="generations per chunk: one progress line and one checkpoint each (default: %(default)s)")
    run.add_argument("--resume", action="store_true",
                     help="continue the run saved in OUT from its checkpoint, with its saved config and seed (no other "
                          "flags needed; flags given must agree with them); without it, a checkpoint in OUT is refused")
    run.add_argument("--out", default="results/run", help="results folder (default: %(default)s)")

    sw = sub.add_parser("sweep", parents=[cache, writes],
                        help="seed sweeps (vmapped, sharded over devices): metrics, Table I, Figure 2",
                        epilog=presets_help() + "\n(each algorithm of a sweep takes the options it has)",
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    add_config_flags(sw, skip=PER_TASK)
    sw.add_argument("--tasks", nargs="+", default=list(registry.registered_tasks()), metavar="TASK",
                    help=f"tasks to sweep: {task_names()} (default: every registered task)")
    sw.add_argument("--algorithms", nargs="+", default=list(SWEPT), choices=algorithms.names(),
                    help=f"default: {' '.join(SWEPT)} (the paper's comparison and this library's M-QD)")
    sw.add_argument("--seeds", type=positive_int, default=None,
                    help="default: the paper's, 25 (2D tasks) or 10 (robot tasks)")
    sw.add_argument("--chunk", type=positive_int, default=25,
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
    ad.add_argument("--goals", type=positive_int, default=1000,
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
    rd.add_argument("--width", type=positive_int, default=320,
                    help="the GIF's width in pixels (default: %(default)s)")
    rd.add_argument("--height", type=positive_int, default=240,
                    help="the GIF's height in pixels (default: %(default)s)")
    return parser, {"run": run, "sweep": sw, "adapt": ad, "plot": pl, "render": rd}


_COMMANDS: dict[str, Callable[[argparse.Namespace], None]] = {
    "run": run_command.run, "sweep": sweep_command.sweep_seeds, "adapt": folder_commands.adapt,
    "plot": folder_commands.plot, "render": folder_commands.render}


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
