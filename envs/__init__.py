"""Tasks for mqd-jax and their registry.

`make(name)` builds a registered task; `register(name, factory)` adds a user's
own (a zero-argument callable returning a `mqd_jax.task.Task`). Tasks are built
once per name and cached, so a name always maps to the same object.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

from mqd_jax.task import Task

_FACTORIES: dict[str, Callable[[], Task]] = {}


def register(name: str, factory: Callable[[], Task]) -> None:
    """Registers a task under `name` (usable as `Config(task=name)`)."""
    if name in _FACTORIES:
        raise ValueError(f"task {name!r} is already registered")
    _FACTORIES[name] = factory
    make.cache_clear()


def registered_tasks() -> tuple[str, ...]:
    return tuple(_FACTORIES)


@functools.cache
def make(name: str) -> Task:
    """The task registered under `name`."""
    if name not in _FACTORIES:
        raise ValueError(f"unknown task {name!r}; registered: {sorted(_FACTORIES)}")
    return _FACTORIES[name]()


def _register_builtin() -> None:
    from envs import object2d, obstacle2d

    register("obstacle2d", obstacle2d.make)
    register("object2d", object2d.make)


_register_builtin()
