"""A run's static configuration (`Config`) and the check of its traced parameters (`check_params`).

`Config` holds what every run has: the task (a registered name, with its
options, or a `Task`), the algorithm (a preset's name, with its
`algorithm_options`, or any `Emitter`), the population, repertoire and archive
sizes, the novelty's k, `t_dist`, the generations and the coverage grid. It is
a frozen, hashable dataclass, so it can be a static argument of `jax.jit`;
every field is validated at construction (and therefore also through
`dataclasses.replace`), before anything is traced: a preset's options against
its function's signature (`mqd_jax.emitters.presets`), the emitter against the run's
size (`Emitter.check_run`).

The traced parameters (`mqd_jax.core.params.Params`, `Config.params()`) are the
engine's `t_dist` and the emitter's own (`Emitter.default_params()`), so one
compiled run can be `jax.vmap`-ed over them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import algorithms, coverage, registry
from mqd_jax.core.checks import check_traced, is_int, is_real
from mqd_jax.core.emitter import Emitter
from mqd_jax.core.params import Params
from mqd_jax.core.task import Task, check_task


def check_params(params: Params, cfg: Config) -> None:
    """Raises ValueError naming the parameter if a concrete value of `params` is NaN, infinite or out of range.

    The engine's `t_dist` (> 0 and <= `cfg.t_dist`: the coverage grid stamps balls of at most the config's
    radius) and the emitter's own, checked by the emitter (`Emitter.check_params`); every element of batched
    params too. Traced values (inside a user's `jit` or `vmap`) cannot be read and are not checked.
    """
    if not isinstance(params, Params):
        raise ValueError(f"params must be a mqd_jax.Params (cfg.params()), not a {type(params).__name__}")
    want = jax.tree.structure(cfg.params().emitter)
    if jax.tree.structure(params.emitter) != want:
        raise ValueError(f"params.emitter does not belong to {cfg.algorithm_name}: expected the structure of "
                         f"cfg.params().emitter ({want})")
    check_traced("Params", "t_dist", params.t_dist, inclusive=False, highest=cfg.t_dist)
    cfg.emitter.check_params(params.emitter)


def _check(ok: bool, name: str, value: Any, allowed: str) -> None:
    if not ok:
        raise ValueError(f"Config.{name}={value!r} is invalid: expected {allowed}")


def _options(given: Any) -> tuple[tuple[str, Any], ...]:
    """Options as given (a mapping, or the pairs a config holds) as sorted pairs."""
    if isinstance(given, Mapping):
        given = given.items()
    try:
        pairs = tuple(sorted((str(k), v.item() if isinstance(v, np.generic) else v) for k, v in given))
    except (TypeError, ValueError):
        raise ValueError(f"Config.algorithm_options={given!r} is invalid: expected a dict of option: value") from None
    return pairs


@dataclasses.dataclass(frozen=True)
class Config:
    """Every static setting of a run. Defaults are Table II's 2D column.

    Attributes:
      task: a registered task's name (`mqd_jax.core.registry`) or a `Task`.
      algorithm: a registered algorithm's name (`mqd_jax.core.algorithms`; the presets "mqd", "mqd-paper", "qd",
        "random") or any `Emitter`.
      algorithm_options: its options (a dict, `mqd_jax.emitters.presets`: `algorithms.options(name)` lists them with
        their defaults); held as the sorted pairs that differ from the defaults, so configs that mean the same
        run compare, hash and save the same.
      max_generations, population_size: the run's length and candidates per generation.
      k: neighbours in the novelty score (and in M-QD's predicted novelty).
      t_dist: insertion distance threshold and coverage ball radius (the default of `Params.t_dist`).
      capacity, archive_capacity: repertoire and rejected-archive sizes (fixed-size masked arrays).
      neighbour_slack: neighbour-list length kept per skill beyond k (longer lists are recomputed less often
        when neighbours are replaced; changes no result).
      coverage_resolution: cells per behavior-space axis of the coverage grid (in one dimension its square: as many
        cells as in two).
      coverage_samples: points of the Monte Carlo coverage estimate, used where the grid does not fit its memory
        bound (`mqd_jax.core.coverage.method`: behavior spaces of 4 or more dimensions, and 3 at the default
        resolution); 2^10 to 2^20. Its standard error is at most 0.5 / sqrt(points).
    """

    task: str | Task = "obstacle2d"
    algorithm: str | Emitter = "qd"
    algorithm_options: Any = ()
    max_generations: int = 250
    population_size: int = 100
    k: int = 5
    t_dist: float = 0.02
    capacity: int = 4096
    archive_capacity: int = 4096
    neighbour_slack: int = 3
    coverage_resolution: int = 256
    coverage_samples: int = 65536

    def __post_init__(self) -> None:
        # numpy scalars (np.int64(10), np.float32(0.02)) become the Python values they hold, so that
        # configs compare, hash and serialize the same however a value was given.
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, np.generic):
                object.__setattr__(self, field.name, value.item())
        if not (isinstance(self.task, Task) or (isinstance(self.task, str) and registry.is_task(self.task))):
            names = registry.registered_tasks()
            _check(False, "task", self.task, f"a Task, one of the registered tasks {sorted(names)} or a plugin "
                   f"'package.module:factory'{registry.did_you_mean(self.task, names)}")
        if isinstance(self.task, Task):
            check_task(self.task, type(self.task).__name__)
        if not (isinstance(self.algorithm, Emitter) or self.algorithm in algorithms.names()):
            _check(False, "algorithm", self.algorithm, f"an Emitter or one of the algorithms {algorithms.names()}"
                   f"{registry.did_you_mean(self.algorithm, algorithms.names())}")
        for name, lo in (("max_generations", 1), ("population_size", 1), ("k", 1), ("capacity", 1),
                         ("archive_capacity", 1), ("neighbour_slack", 0), ("coverage_resolution", 8)):
            v = getattr(self, name)
            _check(is_int(v) and v >= lo, name, v, f"an int >= {lo}")
        low, high = coverage.MIN_SAMPLES, coverage.MAX_SAMPLES
        _check(is_int(self.coverage_samples) and low <= self.coverage_samples <= high, "coverage_samples",
               self.coverage_samples, f"an int from {low} to {high}")
        _check(is_real(self.t_dist) and self.t_dist > 0, "t_dist", self.t_dist, "a finite float > 0")
        _check(self.population_size <= self.capacity, "population_size", self.population_size,
               f"an int <= capacity ({self.capacity})")
        _check(self.k < self.capacity, "k", self.k, f"an int < capacity ({self.capacity}): a skill's k nearest "
               "neighbours are other skills of the repertoire")
        _check(self.capacity < 2**31 and self.archive_capacity < 2**31, "capacity", self.capacity,
               "an int < 2^31 (slots are int32), and so archive_capacity")
        given = _options(self.algorithm_options)
        if isinstance(self.algorithm, Emitter):
            _check(not given, "algorithm_options", dict(given), "{} with an Emitter (it carries its own settings)")
            emitter = self.algorithm
        else:
            defaults = algorithms.options(self.algorithm)
            settings = algorithms.resolved(self.algorithm, dict(given))
            given = tuple((o, v) for o, v in sorted(settings.items()) if v != defaults[o] or type(v) is not
                          type(defaults[o]))
            emitter = algorithms.build(self.algorithm, dict(given), self.k)
        object.__setattr__(self, "algorithm_options", given)
        emitter.check_run(self.population_size, self.max_generations)
        object.__setattr__(self, "_emitter", emitter)

    @property
    def emitter(self) -> Emitter:
        """The emitter a run of this config uses: the preset built with its options, or `algorithm` itself."""
        return self._emitter

    @property
    def options(self) -> dict[str, Any]:
        """Every option of the preset (its defaults with `algorithm_options` over them); {} for an Emitter."""
        if isinstance(self.algorithm, Emitter):
            return {}
        return algorithms.resolved(self.algorithm, dict(self.algorithm_options))

    @classmethod
    def paper_2d(cls, **overrides: Any) -> Config:
        """Table II, 2D column (the 2D Obstacle task unless `task` is given; its `default_t_dist` if it has one)."""
        return cls._column("2d", {}, overrides)

    @classmethod
    def paper_robot(cls, **overrides: Any) -> Config:
        """Table II, robotic column: 100 generations, 64 hidden neurons (for the presets with a model); the task's
        `default_t_dist` if it has one."""
        return cls._column("robot", {"max_generations": 100}, overrides)

    @classmethod
    def _column(cls, column: str, base: dict[str, Any], overrides: dict[str, Any]) -> Config:
        task = overrides.get("task")  # the default task (2D Obstacle) has Table II's t_dist: not made here
        if "t_dist" not in overrides and task is not None:
            made = registry.make(task) if isinstance(task, str) and registry.is_task(task) else task
            if isinstance(made, Task) and made.default_t_dist is not None:  # where Table II's does not fit
                base = {**base, "t_dist": made.default_t_dist}
        algorithm = overrides.get("algorithm", cls.algorithm)
        named = isinstance(algorithm, str) and algorithm in algorithms.names()
        table = algorithms.table_ii(algorithm, column) if named else {}
        options = {**table, **dict(_options(overrides.get("algorithm_options", ())))}
        return cls(**{**base, **overrides, "algorithm_options": options})

    @classmethod
    def paper(cls, task: str, **overrides: Any) -> Config:
        """Table II's column for `task`: the robotic one for the robot tasks, else the 2D one."""
        column = (registry.make(task) if isinstance(task, str) else task).table_ii_column
        return (cls.paper_robot if column == "robot" else cls.paper_2d)(task=task, **overrides)

    @property
    def task_name(self) -> str:
        """The task's registered name, or its class name for a task object `registry.make` did not build."""
        named = registry.name_of(self.task)
        return named[0] if named else type(self.task).__name__

    @property
    def algorithm_name(self) -> str:
        """The preset's name, or the emitter's class name."""
        return self.algorithm if isinstance(self.algorithm, str) else type(self.algorithm).__name__

    def to_dict(self) -> dict[str, Any]:
        """Every field as JSON values (results files, checkpoints): a preset's options all written out (its
        defaults too, so a file keeps its meaning if a default changes). A task `registry.make` built is its name
        (and "task_options" if it was made with options); other task and emitter objects are their repr."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        # A part option left at None (the preset's own part) is not written: files keep their earlier form.
        out["algorithm_options"] = {o: repr(v) if algorithms.is_part(v) else v for o, v in self.options.items()
                                    if v is not None}
        named = registry.name_of(self.task)
        out["task"] = named[0] if named else repr(self.task)
        if named and named[1]:
            out["task_options"] = named[1]
        if not isinstance(self.algorithm, str):
            out["algorithm"] = repr(self.algorithm)
        return out

    @classmethod
    def from_dict(cls, saved: dict[str, Any]) -> Config:
        """The config `to_dict` wrote (a file of an earlier version: `mqd_jax.experiment.migrations.config_from`).
        Raises ValueError for a task or emitter saved as a repr (no name to rebuild it from) or an unknown field."""
        saved = dict(saved)
        options = saved.pop("task_options", None)
        unknown = set(saved) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"a saved config with unknown fields {sorted(unknown)} (from another version?)")
        if saved.get("algorithm") not in algorithms.names():
            raise ValueError(f"a saved config of the emitter {saved.get('algorithm')!r}: only the algorithms "
                             f"{algorithms.names()} can be rebuilt from a file; build its Config in Python")
        task = saved.get("task")
        if not (isinstance(task, str) and registry.is_task(task)):
            raise ValueError(f"a saved config of the task {task!r}, which is not registered here")
        if options:
            saved["task"] = registry.make(task, **options)
        taken = algorithms.part_options(saved["algorithm"])
        parts = {o: v for o, v in dict(saved.get("algorithm_options", {})).items() if o in taken and v is not None}
        if parts:
            raise ValueError(f"a saved config of {saved['algorithm']!r} with the parts {parts}, written as their repr: "
                             "a part object cannot be rebuilt from a file; build its Config in Python")
        return cls(**saved)

    @property
    def neighbours(self) -> int:
        """Length of the neighbour list kept per skill."""
        return self.k + self.neighbour_slack

    def params(self) -> Params:
        """The traced parameters: `t_dist` and the emitter's defaults (`Emitter.default_params()`)."""
        return Params(t_dist=jnp.asarray(self.t_dist, jnp.float32), emitter=self.emitter.default_params())
