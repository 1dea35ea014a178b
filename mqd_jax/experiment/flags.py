"""The command line's flags and the config they give: one flag per `Config` field (`--t-dist 0.03`,
`--population 50`), a preset's options (`-O pool_factor=16`), Table II's columns (`--preset`), each flag's help
with the value it takes when not given."""

from __future__ import annotations

import argparse
import ast
import dataclasses
from typing import Any

from mqd_jax.core import algorithms, registry
from mqd_jax.core.config import Config

# Table II's columns, for `--preset`.
COLUMNS = {"paper-2d": Config.paper_2d, "paper-robot": Config.paper_robot}


# Short flags kept from the first versions of the CLI.
ALIASES = {"max_generations": ["--generations"], "population_size": ["--population"]}


PER_TASK = ("task", "algorithm")  # `sweep` takes these as lists


SWEPT = ("mqd", "mqd-paper", "qd", "random")  # a bare `mqd sweep`'s algorithms


SEEDS = 2**32  # a run's key is PRNGKey(seed): seeds 0 .. 2**32 - 1 give distinct keys


RUN_DEFAULTS = {"max_generations": 100}  # the main job is a short run


def task_names() -> str:
    return ", ".join(registry.registered_tasks()) + ", or a plugin package.module:factory"


def option_value(text: str) -> tuple[str, Any]:
    """argparse type: NAME=VALUE, the value as a Python literal (8, 0.5, True, 'parent'; a bare word is a str)."""
    name, sep, value = text.partition("=")
    if not (sep and name.strip()):
        raise argparse.ArgumentTypeError(f"{text!r} is invalid: expected NAME=VALUE (pool_factor=16)")
    try:
        parsed = ast.literal_eval(value.strip())
    except (ValueError, SyntaxError):
        parsed = value.strip()
    return name.strip(), parsed


def presets_help() -> str:
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


def add_config_flags(parser: argparse.ArgumentParser, skip: tuple[str, ...] = (), preset: str = "auto",
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
    specific = {"task": f"the task: {task_names()}", "algorithm": f"one of {', '.join(algorithms.names())}"}
    for field in dataclasses.fields(Config):
        if field.name in skip or field.name == "algorithm_options":
            continue
        flags = ["--" + field.name.replace("_", "-"), *ALIASES.get(field.name, [])]
        default = _default_text(field.name, defaults, preset)
        text = f"{specific.get(field.name, 'Config.' + field.name)} (default: {default})"
        parser.add_argument(*flags, dest=field.name, type=type(field.default), default=None, help=text)
    parser.add_argument("--algorithm-option", "-O", dest="algorithm_options", type=option_value, nargs="+",
                        action="extend", default=[], metavar="NAME=VALUE",
                        help="an option of the algorithm (repeatable): see the list below; Table II's column sets "
                             "the model's (hidden_size 64 with paper-robot)")


def config_from_flags(args: argparse.Namespace, defaults: dict | None = None, **fixed: str) -> Config:
    """The config the flags give: preset (auto: paper-robot for the robot tasks), then `defaults`, flags, `fixed`.

    In a sweep (several algorithms), each algorithm takes the options it has; an option none of them has is
    refused (`sweep_seeds`)."""
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


def positive_int(text: str) -> int:
    """argparse type: an int >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} is invalid: expected an int >= 1")
    return value


def flag_given(args: argparse.Namespace, flag: str) -> bool:
    """Whether the command line named `flag` (`--preset`, `--seed`)."""
    return any(a == flag or a.startswith(flag + "=") for a in args.argv)


def is_seed(seed: Any) -> bool:
    """Whether `seed` is a seed of `mqd run`: an int from 0 to SEEDS - 1."""
    return isinstance(seed, int) and not isinstance(seed, bool) and 0 <= seed < SEEDS

