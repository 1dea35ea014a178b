"""Algorithm names: the registry that `Config(algorithm="name")` resolves through, as tasks resolve through
`mqd_jax.core.registry`.

An algorithm is a function of keyword options that returns an `Emitter` (`mqd_jax.emitters.presets`, loaded
through the entry point group `mqd_jax.algorithms` before the registry is first read, registers "mqd",
"mqd-paper", "qd" and "random"; `register(name, function)` adds one). Its options are its keyword parameters,
their defaults in its signature; `CONTEXT` names those the config fills in itself (`k`: `Config.k`). An
algorithm may say which of its options Table II sets per column (`table_ii`).
"""

from __future__ import annotations

import functools
import importlib.metadata
import inspect
from collections.abc import Callable, Mapping
from typing import Any

from mqd_jax.core.emitter import Emitter

# Options that are not the user's to give: the config passes its own.
CONTEXT = ("k",)
# Modules that register algorithms when imported (the built-in ones: mqd_jax.emitters.presets), loaded before the
# registry is first read, as the tasks' entry points are.
ENTRY_POINT_GROUP = "mqd_jax.algorithms"
_FUNCTIONS: dict[str, Callable[..., Emitter]] = {}
_TABLE_II: dict[str, Mapping[str, Mapping[str, Any]]] = {}


@functools.cache
def _load_entry_points() -> None:
    for entry in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        entry.load()


def _functions() -> dict[str, Callable[..., Emitter]]:
    """The registered algorithms, the entry points' loaded first."""
    _load_entry_points()
    return _FUNCTIONS


def register(name: str, function: Callable[..., Emitter],
             table_ii: Mapping[str, Mapping[str, Any]] | None = None) -> None:
    """Registers `function` (keyword options -> Emitter) as the algorithm `name`; `table_ii`: {column: options}
    that `Config.paper_2d` / `paper_robot` set. Raises ValueError if `name` is taken."""
    if name in _functions():
        raise ValueError(f"algorithm {name!r} is already registered")
    _FUNCTIONS[name] = function
    _TABLE_II[name] = dict(table_ii or {})


def names() -> tuple[str, ...]:
    """The registered algorithms, in the order they were registered."""
    return tuple(_functions())


def options(name: str) -> dict[str, Any]:
    """{option: default} of the algorithm `name`, without the config's own (`CONTEXT`)."""
    parameters = inspect.signature(_functions()[name]).parameters.values()
    return {p.name: p.default for p in parameters if p.name not in CONTEXT}


def part_options(name: str) -> tuple[str, ...]:
    """The options of the algorithm `name` that take a part (their default is None: the preset's own)."""
    return tuple(o for o, default in options(name).items() if default is None)


def is_part(value: Any) -> bool:
    """Whether an option's value is a part (an object such as a surrogate or a rule), not a plain setting."""
    return value is not None and not isinstance(value, str | int | float | bool | list | tuple | dict)


def resolved(name: str, given: Mapping[str, Any]) -> dict[str, Any]:
    """Every option of the algorithm `name`: its defaults with `given` over them. Raises ValueError for an option
    it does not take, or a value of another type than its default's (an int is a float too); an option whose
    default is None takes a part (an object: `is_part`), given in Python."""
    known = options(name)
    for option, value in given.items():
        if option in CONTEXT:
            raise ValueError(f"algorithm_options: {option!r} is the run's own (Config.{option}), not an option of "
                             f"{name!r}")
        if option not in known:
            listed = ", ".join(f"{o}={d!r}" for o, d in known.items()) or "none"
            raise ValueError(f"algorithm_options: {name!r} takes no option {option!r}; its options: {listed}")
        default = known[option]
        if option in part_options(name):
            if value is not None and not is_part(value):
                raise ValueError(f"algorithm_options: {name}'s {option}={value!r} is invalid: expected a part "
                                 f"object, given in Python ({name}(... {option}=MyPart()) or Config(algorithm_options="
                                 f"{{{option!r}: MyPart()}})), or None for the preset's own")
            continue
        if not (type(value) is type(default) or (type(default) is float and type(value) is int)):
            kind = type(default).__name__
            raise ValueError(f"algorithm_options: {name}'s {option}={value!r} is invalid: expected "
                             f"{'an' if kind[0] in 'aeiou' else 'a'} {kind} (default {default!r})")
    return {**known, **{o: float(v) if type(known[o]) is float else v for o, v in given.items()}}


def build(name: str, given: Mapping[str, Any], k: int) -> Emitter:
    """The emitter of the algorithm `name` with the options `given` (checked: `resolved`) and the run's `k`."""
    settings = resolved(name, given)
    function = _functions()[name]
    if "k" in inspect.signature(function).parameters:
        settings["k"] = k
    return function(**settings)


def table_ii(name: str, column: str) -> dict[str, Any]:
    """The options of Table II's `column` ("2d" or "robot") that the algorithm `name` takes."""
    _load_entry_points()
    return dict(_TABLE_II[name].get(column, {}))
