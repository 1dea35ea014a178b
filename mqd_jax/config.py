"""Static configuration (`Config`) and traced runtime parameters (`Params`).

`Config` holds every hyperparameter of the paper's Table II plus the choices the
paper leaves open. It is a frozen, hashable dataclass, so it can be a static
argument of `jax.jit`; every field is validated at construction (and therefore
also through `dataclasses.replace`), before anything is traced.

`Params` holds the scalar thresholds and rates as a pytree of arrays, so that one
compiled run can be `jax.vmap`-ed over them (the way evosax separates `params`
from the static config). `Config.params()` gives the defaults from the config.

A config names its task (resolved through `mqd_jax.registry`) or holds a
`Task` object, and names a preset emitter ("mqd", "mqd-paper", "qd",
"random"; built by `mqd_jax.presets` from the config's fields) or holds any
`Emitter`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mqd_jax import registry
from mqd_jax.checks import is_int, is_real
from mqd_jax.emitters import Emitter
from mqd_jax.model_emitter import ANCHORS
from mqd_jax.task import Task, check_task

# The named emitters `Config.algorithm` may give (built by `mqd_jax.presets`).
PRESETS = ("mqd", "mqd-paper", "qd", "random")
# The presets with a learned model.
MODEL_PRESETS = ("mqd", "mqd-paper")


@struct.dataclass
class Params:
    """Scalar hyperparameters that may be traced (all float32 scalars)."""

    t_dist: jnp.ndarray
    t_nov: jnp.ndarray
    t_qua: jnp.ndarray
    learning_rate: jnp.ndarray
    iso_sigma: jnp.ndarray
    line_sigma: jnp.ndarray
    adaptation_step_size: jnp.ndarray


# The allowed range of each traced parameter: (name, lowest, whether the lowest is allowed); t_qua: any finite.
_PARAM_RANGES = (("t_dist", 0.0, False), ("learning_rate", 0.0, False), ("adaptation_step_size", 0.0, False),
                 ("t_nov", 0.0, True), ("iso_sigma", 0.0, True), ("line_sigma", 0.0, True),
                 ("t_qua", -math.inf, False))


def check_params(params: Params, cfg: Config) -> None:
    """Raises ValueError naming the field if a concrete `Params` value is NaN, infinite or out of range.

    Checks every element (batched Params too) with the same rules as `Config`, and
    `t_dist <= cfg.t_dist` (the coverage grid stamps disks of at most the config's
    radius). Traced values (inside a user's `jit` or `vmap`) cannot be read and are
    not checked.
    """
    for name, lowest, inclusive in _PARAM_RANGES:
        value = getattr(params, name)
        if isinstance(value, jax.core.Tracer):
            continue
        v = np.asarray(value, np.float64)
        bad = ~np.isfinite(v) | ((v < lowest) if inclusive else (v <= lowest))
        if name == "t_dist":
            bad |= v > np.float32(cfg.t_dist)
        if bad.any():
            allowed = "any finite float" if name == "t_qua" else f"a finite float {'>=' if inclusive else '>'} 0"
            if name == "t_dist":
                allowed += f" and <= Config.t_dist ({cfg.t_dist}; the coverage grid's largest disk)"
            first = float(v.ravel()[np.argmax(bad.ravel())])
            raise ValueError(f"Params.{name}={first!r} is invalid: expected {allowed}")


def _check(ok: bool, name: str, value: Any, allowed: str) -> None:
    if not ok:
        raise ValueError(f"Config.{name}={value!r} is invalid: expected {allowed}")


@dataclasses.dataclass(frozen=True)
class Config:
    """Every hyperparameter of a run. Defaults are Table II's 2D column.

    Shape-determining fields (population, capacity, K, hidden size, generations,
    task, algorithm) are static. The scalar thresholds and rates are also copied
    into `Params` by `params()`, which is what the jitted code reads, so they can
    be overridden by traced values.

    `task` is a registered task's name or a `Task`; `algorithm` a preset's name
    (`PRESETS`) or an `Emitter` (any composition, see `mqd_jax.emitters`). The
    model fields (batch_size, num_batches, warmup_samples, hidden_size,
    pool_factor; "mqd": ensemble_size, optimism, steering_share, anchor, parent_weight, quality_share,
    wide_scale; "mqd-paper": t_nov, t_qua, budgeted) configure the model presets; a composed emitter
    carries its own settings.
    """

    task: str | Task = "obstacle2d"
    algorithm: str | Emitter = "qd"
    max_generations: int = 250
    population_size: int = 100
    k: int = 5
    t_dist: float = 0.02
    t_nov: float = 0.04
    t_qua: float = 0.0
    learning_rate: float = 1e-3
    batch_size: int = 16
    num_batches: int = 500
    warmup_samples: int = 1000
    hidden_size: int = 32
    adaptation_step_size: float = 0.1
    adaptation_steps: int = 10
    # Repertoire and rejected-archive sizes (fixed-size masked arrays).
    capacity: int = 4096
    archive_capacity: int = 4096
    # Iso+line variation (Vassiliades & Mouret 2018): Gaussian mutation with
    # std `iso_sigma` times the action range, plus a crossover step of std
    # `line_sigma` along the line between the two parents.
    iso_sigma: float = 0.02
    line_sigma: float = 0.1
    # Neighbour-list length kept per skill (>= k); longer lists are recomputed
    # less often when neighbours are replaced. Does not change any result.
    neighbour_slack: int = 3
    # Cells per behavior-space axis of the coverage grid.
    coverage_resolution: int = 256
    # "mqd" (acquisition.Diverse) and budgeted "mqd-paper" choose the
    # population from `pool_factor` x as many candidates.
    pool_factor: int = 8
    # "mqd": the model's ensemble members (one network: four were no better and
    # twice as slow, docs/results.md), and the weight of their spread in the
    # optimistic distance to the nearest skill (acquisition.greedy_diverse).
    ensemble_size: int = 1
    optimism: float = 1.0
    # "mqd": the share of the pool replaced by children the model's Jacobian
    # aims at empty behavior space (steering.Steering; 0 = none, version 0.4's "mqd").
    steering_share: float = 0.25
    # "mqd": where the model's predictions are anchored (ModelEmitter.anchor): "parent", the skill a
    # candidate was varied from, or "nearest", the nearest skill in action space (a search; version 0.5's).
    anchor: str = "parent"
    # "mqd": the exponent of a predicted opener's parent's relative novelty in its rank (acquisition.Diverse's
    # parent_weight; 0 = the predicted distance alone, version 0.6's "mqd").
    parent_weight: float = 1.0
    # "mqd": the share of the rule's choices that go first to predicted quality gains in held niches
    # (acquisition.Diverse's quality_share; 0 = none, version 0.7's "mqd").
    quality_share: float = 0.1
    # "mqd": half of the pool's children vary at `wide_scale` x both iso+line steps
    # (IsoLine(scales=(1, wide_scale))); 1 = one scale, version 0.8's "mqd".
    wide_scale: float = 2.0
    # Budgeted ranking ("mqd-paper" only; off is the paper's threshold filter):
    # rank `pool_factor` x population candidates with the model and evaluate
    # exactly `population_size` of them (see acquisition.Budgeted).
    budgeted: bool = False

    def __post_init__(self) -> None:
        # numpy scalars (np.int64(10), np.float32(0.02)) become the Python values they hold, so that
        # configs compare, hash and serialize the same however a value was given.
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, np.generic):
                object.__setattr__(self, field.name, value.item())
        _check(isinstance(self.task, Task) or (isinstance(self.task, str) and registry.is_task(self.task)), "task",
               self.task, f"a Task, one of the registered tasks {sorted(registry.registered_tasks())} or a plugin "
               "'package.module:factory'")
        if isinstance(self.task, Task):
            check_task(self.task, type(self.task).__name__)
        _check(isinstance(self.algorithm, Emitter) or self.algorithm in PRESETS, "algorithm", self.algorithm,
               f"an Emitter or one of the presets {PRESETS}")
        for name, lo in (("max_generations", 1), ("population_size", 1), ("k", 1),
                         ("batch_size", 1), ("num_batches", 1), ("warmup_samples", 0),
                         ("hidden_size", 1), ("adaptation_steps", 0), ("capacity", 1),
                         ("archive_capacity", 1), ("neighbour_slack", 0),
                         ("coverage_resolution", 8), ("pool_factor", 1), ("ensemble_size", 1)):
            v = getattr(self, name)
            _check(is_int(v) and v >= lo, name, v, f"an int >= {lo}")
        for name in ("t_dist", "learning_rate", "adaptation_step_size"):
            v = getattr(self, name)
            _check(is_real(v) and v > 0, name, v, "a finite float > 0")
        for name in ("t_nov", "iso_sigma", "line_sigma", "optimism", "parent_weight"):
            v = getattr(self, name)
            _check(is_real(v) and v >= 0, name, v, "a finite float >= 0")
        _check(is_real(self.t_qua), "t_qua", self.t_qua, "a finite float")
        _check(isinstance(self.budgeted, bool), "budgeted", self.budgeted, "a bool")
        _check(not self.budgeted or self.algorithm == "mqd-paper", "budgeted", self.budgeted,
               f"False unless algorithm='mqd-paper' (it is {self.algorithm!r})")
        _check(is_real(self.steering_share) and 0 <= self.steering_share < 1, "steering_share", self.steering_share,
               "a float in [0, 1)")
        _check(is_real(self.quality_share) and 0 <= self.quality_share <= 1, "quality_share", self.quality_share,
               "a float in [0, 1]")
        _check(is_real(self.wide_scale) and self.wide_scale > 0, "wide_scale", self.wide_scale, "a finite float > 0")
        _check(self.anchor in ANCHORS, "anchor", self.anchor, f"one of {ANCHORS}")
        pool = self.pool_factor * self.population_size
        steered = round(self.steering_share * pool)
        _check(self.algorithm != "mqd" or self.steering_share == 0 or 1 <= steered <= pool - self.population_size,
               "steering_share", self.steering_share, f"0, or a share of 'mqd''s pool of {pool} (pool_factor x "
               "population_size) that steers at least one child and leaves population_size unsteered")
        budget = self.max_generations * self.population_size
        _check(self.algorithm not in MODEL_PRESETS or self.warmup_samples < budget, "warmup_samples",
               self.warmup_samples,
               f"an int < max_generations * population_size ({budget}) for M-QD, or the model is never used")
        _check(self.population_size <= self.capacity, "population_size", self.population_size,
               f"an int <= capacity ({self.capacity})")

    @classmethod
    def paper_2d(cls, **overrides: Any) -> Config:
        """Table II, 2D column (the 2D Obstacle task unless `task` is given)."""
        return cls(**overrides)

    @classmethod
    def paper_robot(cls, **overrides: Any) -> Config:
        """Table II, robotic column: 100 generations, 64 hidden neurons."""
        base = dict(max_generations=100, hidden_size=64)
        return cls(**{**base, **overrides})

    @classmethod
    def paper(cls, task: str, **overrides: Any) -> Config:
        """Table II's column for `task`: the robotic one for the KUKA tasks, else the 2D one."""
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
        """Every field as JSON values (results files, checkpoints). A task `registry.make` built is its name (and
        "task_options" if it was made with options); other task and emitter objects are their repr."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        named = registry.name_of(self.task)
        out["task"] = named[0] if named else repr(self.task)
        if named and named[1]:
            out["task_options"] = named[1]
        if not isinstance(self.algorithm, str):
            out["algorithm"] = repr(self.algorithm)
        return out

    @classmethod
    def from_dict(cls, saved: dict[str, Any]) -> Config:
        """The config `to_dict` wrote (or an earlier version, see `upgraded`). Raises ValueError for a task or
        emitter saved as a repr (no name to rebuild it from) or an unknown field."""
        saved = upgraded(saved)
        options = saved.pop("task_options", None)
        unknown = set(saved) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"a saved config with unknown fields {sorted(unknown)} (from another version?)")
        if saved.get("algorithm") not in PRESETS:
            raise ValueError(f"a saved config of the emitter {saved.get('algorithm')!r}: only presets {PRESETS} can "
                             "be rebuilt from a file; build its Config in Python")
        task = saved.get("task")
        if not (isinstance(task, str) and registry.is_task(task)):
            raise ValueError(f"a saved config of the task {task!r}, which is not registered here")
        if options:
            saved["task"] = registry.make(task, **options)
        return cls(**saved)

    @property
    def neighbours(self) -> int:
        """Length of the neighbour list kept per skill."""
        return self.k + self.neighbour_slack

    def params(self) -> Params:
        """The traced scalar parameters, initialised from this config."""
        f = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        return Params(
            t_dist=f(self.t_dist), t_nov=f(self.t_nov), t_qua=f(self.t_qua),
            learning_rate=f(self.learning_rate), iso_sigma=f(self.iso_sigma),
            line_sigma=f(self.line_sigma), adaptation_step_size=f(self.adaptation_step_size),
        )


def upgraded(saved: dict[str, Any]) -> dict[str, Any]:
    """A config dict saved by an earlier version in today's fields: `physics_backend` "auto" is dropped (since
    version 0.2 a robot task's backend is an option of its construction, `task_options`); before version 0.3
    (configs without `ensemble_size`) "mqd" was the paper's filter, today's "mqd-paper", and `pool_factor`
    defaulted to 4; before version 0.5 (configs without `steering_share`) "mqd" did not steer; before version
    0.6 (configs without `anchor`) it anchored at the nearest skill; before version 0.7 (configs without
    `parent_weight`) it ranked predicted openers by their distance alone; before version 0.8 (configs without
    `quality_share`) it made no quality steps; before version 0.9 (configs without `wide_scale`) it varied its
    pool at one scale."""
    saved = dict(saved)
    if "ensemble_size" not in saved:
        saved.setdefault("pool_factor", 4)
        if saved.get("algorithm") == "mqd":
            saved["algorithm"] = "mqd-paper"
        for name in ("ensemble_size", "optimism"):  # fields that did not exist: today's defaults
            saved[name] = Config.__dataclass_fields__[name].default
    if "steering_share" not in saved:  # before version 0.5 "mqd" did not steer
        saved["steering_share"] = 0.0 if saved.get("algorithm") == "mqd" else Config.steering_share
    if "anchor" not in saved:  # before version 0.6 "mqd" anchored at the nearest skill
        saved["anchor"] = "nearest" if saved.get("algorithm") == "mqd" else Config.anchor
    if "parent_weight" not in saved:  # before version 0.7 "mqd" ranked by the predicted distance alone
        saved["parent_weight"] = 0.0 if saved.get("algorithm") == "mqd" else Config.parent_weight
    if "quality_share" not in saved:  # before version 0.8 "mqd" made no quality steps
        saved["quality_share"] = 0.0 if saved.get("algorithm") == "mqd" else Config.quality_share
    if "wide_scale" not in saved:  # before version 0.9 "mqd" varied its pool at one scale
        saved["wide_scale"] = 1.0 if saved.get("algorithm") == "mqd" else Config.wide_scale
    backend = saved.pop("physics_backend", "auto")
    if backend != "auto":
        saved["task_options"] = {**saved.get("task_options", {}), "backend": backend}
    return saved
