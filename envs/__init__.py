"""Tasks for mqd-jax and their registry.

`make(name)` builds a registered task; `register(name, factory)` adds a user's
own (a zero-argument callable returning a `mqd_jax.task.Task`). Tasks are built
once per name and cached, so a name always maps to the same object.

Tasks from other packages, without registering them in Python first (so that
`mqd run --task ...` can use them):

* a plugin name `"package.module:factory"`: the module is imported and
  `factory` registered under that name the first time it is used;
* an entry point in the group `mqd_jax.tasks` of an installed package
  (`[project.entry-points."mqd_jax.tasks"] reach = "my_pkg.tasks:make_reach"`
  in its pyproject.toml): registered under the entry point's name.
"""

from __future__ import annotations

import functools
import importlib
import importlib.metadata
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


ENTRY_POINT_GROUP = "mqd_jax.tasks"


@functools.cache
def _register_entry_points() -> None:
    """Registers the tasks of installed packages' `mqd_jax.tasks` entry points (once per process)."""
    for entry in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        if entry.name not in _FACTORIES:
            _FACTORIES[entry.name] = lambda entry=entry, **options: entry.load()(**options)


def _register_plugin(name: str) -> bool:
    """Registers the plugin name `"package.module:factory"` on first use; whether `name` is one."""
    module, _, attribute = name.partition(":")
    if not (module and attribute) or name in _FACTORIES:
        return False
    try:
        factory = getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"task {name!r}: cannot load the factory {attribute!r} from module {module!r} ({e})") from e
    if not callable(factory):
        raise ValueError(f"task {name!r}: {module}.{attribute} is not callable")
    register(name, factory)
    return True


def registered_tasks() -> tuple[str, ...]:
    """The names of the registered tasks: the built-in ones first, then entry points and the user's."""
    _register_entry_points()
    return tuple(_FACTORIES)


def is_task(name: str) -> bool:
    """Whether `name` is a registered task, an installed entry point or a loadable plugin name."""
    return name in registered_tasks() or _register_plugin(name)


@functools.cache
def make(name: str, **options: Any) -> Task:
    """The task registered under `name`; `options` go to its factory (robot tasks take `backend`)."""
    if not is_task(name):
        raise ValueError(f"unknown task {name!r}; registered: {sorted(_FACTORIES)}, or give "
                         "'package.module:factory'")
    try:
        task = _FACTORIES[name](**options)
    except Exception as e:  # a user's factory may fail in any way: say which task it was
        given = f" with the options {options}" if options else ""
        raise ValueError(f"task {name!r}: its factory failed{given} ({type(e).__name__}: {e})") from e
    if not isinstance(task, Task):
        raise ValueError(f"task {name!r}: its factory returned a {type(task).__name__}, not a mqd_jax.Task")
    return task


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
