"""Tasks for mqd-jax and their registry.

`make(name)` builds a registered task; `register(name, factory)` adds a user's
own (a zero-argument callable returning a `mqd_jax.task.Task`). Tasks are built
once per name and cached, so a name always maps to the same object.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

from mqd_jax.task import Task

_FACTORIES: dict[str, Callable[..., Task]] = {}
# The KUKA tasks: the paper's robotic column of Table II, 10 seeds.
ROBOT_TASKS = ("push_cube", "push_sphere", "place")


def register(name: str, factory: Callable[[], Task]) -> None:
    """Registers a task under `name` (usable as `Config(task=name)`)."""
    if name in _FACTORIES:
        raise ValueError(f"task {name!r} is already registered")
    _FACTORIES[name] = factory
    make.cache_clear()


def registered_tasks() -> tuple[str, ...]:
    return tuple(_FACTORIES)


@functools.cache
def make(name: str, **options: Any) -> Task:
    """The task registered under `name`; `options` go to its factory (robot tasks take `backend`)."""
    if name not in _FACTORIES:
        raise ValueError(f"unknown task {name!r}; registered: {sorted(_FACTORIES)}")
    try:
        return _FACTORIES[name](**options)
    except TypeError as e:
        if not options:
            raise
        raise ValueError(f"task {name!r} does not take the options {options}: {e}") from e


def _register_builtin() -> None:
    from envs import object2d, obstacle2d

    register("obstacle2d", obstacle2d.make)
    register("object2d", object2d.make)

    def push(scene: str, height: float) -> Callable[..., Task]:
        def build(backend: str = "auto") -> Task:
            from envs import push  # imports mujoco only when a robot task is built

            return push.make(scene, height, backend=backend)

        return build

    register("push_cube", push("push_cube", 0.025))
    register("push_sphere", push("push_sphere", 0.03))

    def place(backend: str = "auto") -> Task:
        from envs import place

        return place.make(backend=backend)

    register("place", place)


_register_builtin()
