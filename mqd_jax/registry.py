"""Task names: the registry that `Config(task="name")` resolves through.

`make(name)` builds a registered task; `register(name, factory)` adds a user's
own (a callable returning a `mqd_jax.task.Task`). Tasks are built once per name
and options and cached, so a name always maps to the same object.

The registry is filled without this package importing any task package:

* entry points in the group `mqd_jax.tasks` of installed packages
  (`[project.entry-points."mqd_jax.tasks"] reach = "my_pkg.tasks:make_reach"`
  in a pyproject.toml): the built-in tasks of `envs` are registered this way,
  and their modules are imported only when a task is made;
* a plugin name `"package.module:factory"`: the module is imported and
  `factory` registered under that name the first time it is used;
* `register(name, factory)` from Python.
"""

from __future__ import annotations

import functools
import importlib
import importlib.metadata
from collections.abc import Callable
from typing import Any

from mqd_jax.task import Task

ENTRY_POINT_GROUP = "mqd_jax.tasks"
_FACTORIES: dict[str, Callable[..., Task]] = {}
# (name, options) of every task `make` built, by the task's id: how a config names its task in a results file.
_MADE: dict[int, tuple[str, dict[str, Any]]] = {}


def register(name: str, factory: Callable[..., Task]) -> None:
    """Registers a task under `name` (usable as `Config(task=name)`)."""
    if name in registered_tasks():
        raise ValueError(f"task {name!r} is already registered")
    _FACTORIES[name] = factory


@functools.cache
def _entry_points() -> dict[str, importlib.metadata.EntryPoint]:
    """The installed packages' `mqd_jax.tasks` entry points by name (read once per process)."""
    return {entry.name: entry for entry in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}


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
    """The names of the registered tasks: entry points (the built-in ones first) and then the user's."""
    return (*_entry_points(), *(name for name in _FACTORIES if name not in _entry_points()))


def is_task(name: str) -> bool:
    """Whether `name` is a registered task, an installed entry point or a loadable plugin name."""
    return name in registered_tasks() or _register_plugin(name)


def make(name: str, **options: Any) -> Task:
    """The task registered under `name`; `options` go to its factory (robot tasks take `backend`)."""
    if not is_task(name):
        raise ValueError(f"unknown task {name!r}; registered: {sorted(registered_tasks())}, or give "
                         "'package.module:factory'")
    return _make(name, tuple(sorted(options.items())))


@functools.cache
def _make(name: str, options: tuple[tuple[str, Any], ...]) -> Task:
    factory = _FACTORIES[name] if name in _FACTORIES else _entry_points()[name].load()
    try:
        task = factory(**dict(options))
    except Exception as e:  # a user's factory may fail in any way: say which task it was
        given = f" with the options {dict(options)}" if options else ""
        raise ValueError(f"task {name!r}: its factory failed{given} ({type(e).__name__}: {e})") from e
    if not isinstance(task, Task):
        raise ValueError(f"task {name!r}: its factory returned a {type(task).__name__}, not a mqd_jax.Task")
    _MADE[id(task)] = (name, dict(options))
    return task


def name_of(task: str | Task) -> tuple[str, dict[str, Any]] | None:
    """(name, options) that `make` builds `task` from; a name stands for itself; None for other task objects."""
    if isinstance(task, str):
        return task, {}
    return _MADE.get(id(task))
