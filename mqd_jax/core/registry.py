"""Task names: the registry that `Config(task="name")` resolves through.

`make(name)` builds a registered task; `register(name, factory)` adds a user's
own (a callable returning a `mqd_jax.core.task.Task`). Tasks are built once per name
and options and cached, so a name always maps to the same object.

The registry is filled without this package importing any task package:

* entry points in the group `mqd_jax.tasks` of installed packages
  (`[project.entry-points."mqd_jax.tasks"] reach = "my_pkg.tasks:make_reach"`
  in a pyproject.toml): the built-in tasks of `envs` are registered this way,
  and their modules are imported only when a task is made;
* a plugin name `"package.module:factory"`: the module is imported and
  `factory` registered under that name the first time it is used;
* `register(name, factory)` from Python.

A name stands for one implementation. Registering a name that is already
taken (a built-in, an entry point of another package, a plugin or an earlier
`register`) raises a ValueError naming both sources; `register(name, factory,
replace=True)` replaces it on purpose. Two installed packages whose entry
points share a name make that name unusable until one of them is chosen with
`register(..., replace=True)` (or uninstalled): the error names both.
`source(name)` says which implementation a name stands for; results files
record it, and a results folder refuses to mix implementations of one task.
"""

from __future__ import annotations

import difflib
import functools
import importlib
import importlib.metadata
from collections.abc import Callable
from typing import Any

import jax

from mqd_jax.core.task import Task, check_task
from mqd_jax.version import __version__

ENTRY_POINT_GROUP = "mqd_jax.tasks"
BUILT_IN = "mqd-jax"  # the distribution whose entry points are the built-in tasks
_FACTORIES: dict[str, Callable[..., Task]] = {}
_SOURCES: dict[str, str] = {}  # how each name in _FACTORIES was registered
# (name, options) of every task `make` built, by the task's id: how a config names its task in a results file.
_MADE: dict[int, tuple[str, dict[str, Any]]] = {}
# Called when a name changes implementation: a config names its task by name, so whatever was computed or
# compiled for a config (jitted programs, the engine's per-config caches) may belong to the old one.
_ON_REPLACE: list[Callable[[], None]] = [jax.clear_caches]


def on_replace(clear: Callable[[], None]) -> None:
    """Registers `clear`, called whenever a task name is given another implementation (a per-config cache's
    `cache_clear`)."""
    _ON_REPLACE.append(clear)


def _describe(factory: Callable[..., Task]) -> str:
    return f"{getattr(factory, '__module__', '?')}:{getattr(factory, '__qualname__', repr(factory))}"


def register(name: str, factory: Callable[..., Task], replace: bool = False, _source: str | None = None) -> None:
    """Registers a task under `name` (usable as `Config(task=name)`).

    Raises ValueError, naming both sources, if `name` is already registered, unless `replace` (on purpose).
    """
    if not callable(factory):
        raise ValueError(f"task {name!r}: the factory {factory!r} is not callable")
    new = _source or f"registry.register ({_describe(factory)})"
    replacing = name in registered_tasks()
    if replacing and not replace:
        raise ValueError(f"task {name!r} is already registered by {_sources(name)}; registering it again by {new} "
                         "would replace it: pass replace=True to do so on purpose, or choose another name")
    _FACTORIES[name], _SOURCES[name] = factory, new
    _make.cache_clear()
    if replacing:
        for clear in _ON_REPLACE:
            clear()


def _entry_source(entry: importlib.metadata.EntryPoint) -> str:
    dist = entry.dist
    if dist is not None and dist.name == BUILT_IN:
        return f"built-in ({BUILT_IN} {__version__}, {entry.value})"
    owner = f"{dist.name} {dist.version}" if dist is not None else "an unknown distribution"
    return f"entry point {entry.value} of {owner}"


@functools.cache
def _entry_points() -> dict[str, tuple[importlib.metadata.EntryPoint, ...]]:
    """The installed packages' `mqd_jax.tasks` entry points by name, several where packages clash (read once
    per process; a distribution installed twice on the path counts once)."""
    found: dict[str, dict[str, importlib.metadata.EntryPoint]] = {}
    for entry in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        found.setdefault(entry.name, {}).setdefault(_entry_source(entry), entry)
    built_in_first = lambda e: not _entry_source(e).startswith("built-in")  # noqa: E731
    return {name: tuple(sorted(by_source.values(), key=built_in_first)) for name, by_source in found.items()}


def _sources(name: str) -> str:
    """The source(s) `name` is registered by, in words."""
    if name in _FACTORIES:
        return _SOURCES[name]
    return " and ".join(_entry_source(e) for e in _entry_points().get(name, ()))


def source(name: str) -> str:
    """Which implementation the task `name` stands for: "built-in (mqd-jax VERSION, module:factory)", "entry
    point module:factory of DIST VERSION", "plugin module:factory" or "registry.register (module:factory)".

    Raises ValueError if two installed packages register `name` and neither was chosen.
    """
    if name not in _FACTORIES and len(_entry_points().get(name, ())) > 1:
        raise ValueError(f"task {name!r} is registered twice: by {_sources(name)}; choose one with "
                         f"mqd_jax.core.registry.register({name!r}, factory, replace=True), or uninstall the other")
    if not is_task(name):
        raise ValueError(f"unknown task {name!r}")
    return _sources(name)


def _register_plugin(name: str) -> bool:
    """Registers the plugin name `"package.module:factory"` on first use; whether `name` is one."""
    module, _, attribute = name.partition(":")
    if not (module and attribute) or name in _FACTORIES:
        return False
    if not all(part.isidentifier() for part in (*module.split("."), attribute)):
        raise ValueError(f"task {name!r} is neither a registered task nor a plugin 'package.module:factory' (dotted "
                         f"Python names): registered: {', '.join(registered_tasks())}")
    try:
        factory = getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError) as e:
        hint = (f"; is {module.split('.')[0]!r} on the Python path? Run from the folder that holds it with "
                "PYTHONPATH=. (or install it: pip install -e . in its folder)" if isinstance(e, ImportError) else "")
        raise ValueError(f"task {name!r}: cannot load the factory {attribute!r} from module {module!r} ({e}){hint}"
                         ) from e
    if not callable(factory):
        raise ValueError(f"task {name!r}: {module}.{attribute} is not callable")
    register(name, factory, _source=f"plugin {name}")
    return True


def did_you_mean(name: str, names: Any) -> str:
    """' (did you mean 'X'?)' for the name in `names` nearest to a mistyped `name` (difflib), or ''."""
    near = difflib.get_close_matches(str(name), [str(n) for n in names], n=1, cutoff=0.6)
    return f" (did you mean {near[0]!r}?)" if near else ""


def registered_tasks() -> tuple[str, ...]:
    """The names of the registered tasks: entry points (the built-in ones first) and then the user's."""
    return (*_entry_points(), *(name for name in _FACTORIES if name not in _entry_points()))


def is_task(name: str) -> bool:
    """Whether `name` is a registered task, an installed entry point or a loadable plugin name."""
    return name in registered_tasks() or _register_plugin(name)


def make(name: str, **options: Any) -> Task:
    """The task registered under `name`; `options` go to its factory (robot tasks take `backend`)."""
    if not is_task(name):
        raise ValueError(f"unknown task {name!r}{did_you_mean(name, registered_tasks())}; registered: "
                         f"{sorted(registered_tasks())}, or give 'package.module:factory'")
    source(name)  # refuses a name two packages register
    return _make(name, tuple(sorted(options.items())))


def _load(name: str) -> Callable[..., Task]:
    if name in _FACTORIES:
        return _FACTORIES[name]
    (entry,) = _entry_points()[name]
    try:
        return entry.load()
    except (ImportError, AttributeError) as e:
        raise ValueError(f"task {name!r}: cannot load its factory {entry.value} ({_entry_source(entry)}): "
                         f"{type(e).__name__}: {e}; reinstall that package, or fix its entry point") from e


@functools.cache
def _make(name: str, options: tuple[tuple[str, Any], ...]) -> Task:
    factory = _load(name)
    try:
        task = factory(**dict(options))
    except Exception as e:  # a user's factory may fail in any way: say which task it was
        given = f" with the options {dict(options)}" if options else ""
        raise ValueError(f"task {name!r}: its factory failed{given} ({type(e).__name__}: {e})") from e
    if not isinstance(task, Task):
        raise ValueError(f"task {name!r}: its factory returned a {type(task).__name__}, not a mqd_jax.Task")
    check_task(task, name)
    _MADE[id(task)] = (name, dict(options))
    return task


def name_of(task: str | Task) -> tuple[str, dict[str, Any]] | None:
    """(name, options) that `make` builds `task` from; a name stands for itself; None for other task objects."""
    if isinstance(task, str):
        return task, {}
    return _MADE.get(id(task))
