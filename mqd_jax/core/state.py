"""A run's state and what is decided before its first generation: the `State` a run carries from one generation to
the next, its metrics' names and dtypes, `init` (the state before the first generation), and the checks made before
anything is traced (`check_size`: memory; `check_state`: shapes and dtypes of a state against its config).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import archive as archive_lib
from mqd_jax.core import coverage, pytree, registry, repertoire, sizes
from mqd_jax.core.config import Config
from mqd_jax.core.emitter import init_emitter
from mqd_jax.core.task import Task, check_outputs, feature_dim

# The metrics of every generation (scalars; see `run_mqd`) and their dtypes; the emitter adds its own
# (`metric_dtypes`). A skipped generation reports zeros of these without tracing a generation to find out.
METRICS = {
    "coverage": jnp.float32, "mean_quality": jnp.float32, "max_quality": jnp.float32, "qd_score": jnp.float32,
    "repertoire_size": jnp.int32,
    "num_evaluations": jnp.int32, "evaluations": jnp.int32, "added": jnp.int32, "replaced": jnp.int32,
    "rejected": jnp.int32, "dropped_full": jnp.int32, "invalid": jnp.int32, "out_of_range": jnp.int32,
    "out_of_box": jnp.int32, "insertion_rounds": jnp.int32,
}


@pytree.dataclass
class State:
    """Everything a run carries from one generation to the next.

    Attributes:
      repertoire: the skills found so far (capacity C).
      archive: skills rejected or replaced (ring buffer of size A).
      coverage: the repertoire's balls' counts on the coverage grid or Monte Carlo points.
      emitter: the emitter's state (M-QD: `model_emitter.ModelEmitterState`, which holds the model).
      key: PRNG key for the next generation.
      generation: int32, generations done.
      num_evaluations: int32, rollouts evaluated so far.
    """

    repertoire: repertoire.Repertoire
    archive: archive_lib.Archive
    coverage: coverage.Grid | coverage.Samples
    emitter: Any
    key: jax.Array
    generation: jax.Array
    num_evaluations: jax.Array


def stage(name: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Names a stage of the generation: its operations run under `jax.named_scope(name)`, so a profile (or the
    lowered program) shows where the time goes. Names only: the computation is unchanged."""
    def named(f: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(f)
        def staged(*args: Any, **kwargs: Any) -> Any:
            with jax.named_scope(name):
                return f(*args, **kwargs)
        return staged
    return named


def get_task(cfg: Config) -> Task:
    """The task of `cfg`: its Task, or the one `mqd_jax.core.registry` makes from its name."""
    return registry.make(cfg.task) if isinstance(cfg.task, str) else cfg.task


def metric_dtypes(cfg: Config) -> dict[str, Any]:
    """{name: dtype} of a generation's metrics: the engine's (`METRICS`) and the emitter's."""
    return {**METRICS, **cfg.emitter.metrics()}


def coverage_method(cfg: Config) -> str:
    """How `cfg`'s coverage is measured: `coverage.GRID` (cell centres) or `coverage.MONTE_CARLO` (with its
    standard error), whichever fits the memory bounds (`coverage.method`); decided before anything is allocated."""
    task = get_task(cfg)
    return coverage.method(np.asarray(task.behavior_low), np.asarray(task.behavior_high), cfg.coverage_resolution,
                           cfg.t_dist, 2 * cfg.population_size)


@functools.cache
def coverage_points(cfg: Config) -> tuple[np.ndarray | None, np.ndarray]:
    """Where `cfg`'s coverage is measured, computed once per config: (None, reachable [G] * d cells) for a grid,
    (points [M, d], reachable [M]) for a Monte Carlo estimate."""
    task = get_task(cfg)
    low, high = np.asarray(task.behavior_low), np.asarray(task.behavior_high)
    if coverage_method(cfg) == coverage.GRID:
        return None, task.reachable(coverage.cell_centres(low, high, coverage.axis_cells(len(low),
                                                                                       cfg.coverage_resolution)))
    points = coverage.sample_points(low, high, cfg.coverage_samples)
    return points, task.reachable(points)


def _empty_coverage(cfg: Config) -> coverage.Grid | coverage.Samples:
    task = get_task(cfg)
    points, reachable = coverage_points(cfg)
    if points is None:
        return coverage.empty(np.asarray(task.behavior_low), np.asarray(task.behavior_high), reachable, cfg.t_dist)
    return coverage.empty_samples(points, reachable)


def init(key: jax.Array, cfg: Config) -> State:
    """The state before the first generation: empty repertoire and archive, the emitter's initial state. Jitted.

    Raises ValueError if the task's `evaluate` breaks the task protocol's shapes, if `t_dist` is at least the
    behavior box's diagonal (one skill would hold the whole box), or the emitter cannot serve the task
    (`Emitter.check_task`: a gate needs an auxiliary output the task does not return).
    """
    task = get_task(cfg)
    diagonal = float(np.linalg.norm(np.subtract(task.behavior_high, task.behavior_low)))
    if cfg.t_dist >= diagonal:
        raise ValueError(f"Config.t_dist={cfg.t_dist!r} is invalid for the task {cfg.task_name!r}: its behavior box's "
                         f"diagonal is {diagonal:.4g}, so a single skill would hold the whole box; expected t_dist < "
                         f"{diagonal:.4g}")
    check_outputs(task, cfg.task_name, cfg.population_size)
    cfg.emitter.check_task(task)
    check_size(cfg)
    return _init(key, cfg)


def check_size(cfg: Config, runs: int = 1) -> int:
    """Raises ValueError, naming the bytes needed, if `runs` runs of `cfg` cannot fit in the device's memory
    (`mqd_jax.core.sizes`); returns the bytes estimated. Nothing is traced but the state's shapes."""
    return sizes.check(_state_shapes(cfg), cfg.population_size, cfg.emitter.pool_size(cfg.population_size),
                       cfg.capacity, cfg.archive_capacity, runs)


@functools.partial(jax.jit, static_argnames="cfg")
def _init(key: jax.Array, cfg: Config) -> State:
    # One compiled program rather than a few dozen eager operations: a second start loads it from the cache.
    task = get_task(cfg)
    n, d = task.action_dim, task.behavior_dim
    key, k_emitter = jax.random.split(key)
    return State(
        repertoire=repertoire.Repertoire.empty(cfg.capacity, n, d, cfg.neighbours, kept_features(cfg)),
        archive=archive_lib.Archive.empty(cfg.archive_capacity, n, d),
        coverage=_empty_coverage(cfg),
        emitter=init_emitter(cfg.emitter, k_emitter, task, cfg.capacity),
        key=key,
        generation=jnp.int32(0),
        num_evaluations=jnp.int32(0),
    )


def kept_features(cfg: Config) -> int:
    """How many features per skill the repertoire keeps for the config's emitter (`Emitter.keeps_features`)."""
    task = get_task(cfg)
    return feature_dim(task) if cfg.emitter.keeps_features(task) else 0


@functools.cache
def _state_shapes(cfg: Config) -> State:
    """The shapes and dtypes of a state of `cfg` (abstract: nothing runs)."""
    return jax.eval_shape(lambda k: _init(k, cfg), jax.ShapeDtypeStruct((2,), jnp.uint32))


def check_state(state: State, cfg: Config, batch: tuple[int, ...] = (), fields: tuple[str, ...] | None = None) -> None:
    """Raises ValueError unless every array of `state` has the shape and dtype a state of `cfg` has.

    `batch` is a leading batch shape (a sweep's states: (S,)); `fields` limits the
    check to these fields of the state (default: all). Catches a state of another
    task, capacity or model size passed with the wrong config (tracers too:
    shapes are static). Tasks with the same action and behavior sizes cannot be
    told apart this way.
    """
    want = _state_shapes(cfg)
    if fields is not None:
        want, state = ({f: getattr(s, f) for f in fields} for s in (want, state))
    want, structure = jax.tree_util.tree_flatten_with_path(want)
    got, got_structure = jax.tree_util.tree_flatten(state)
    if got_structure != structure:
        why = "a state of another structure"
    else:
        why = next((f"state{jax.tree_util.keystr(path)} is {jnp.result_type(g)}{list(np.shape(g))}, expected "
                    f"{w.dtype}{[*batch, *w.shape]}" for (path, w), g in zip(want, got, strict=True)
                    if tuple(np.shape(g)) != (*batch, *w.shape) or jnp.result_type(g) != w.dtype), None)
    if why is not None:
        raise ValueError(f"the state does not belong to this config (task {cfg.task!r}, capacity {cfg.capacity}, "
                         f"algorithm {cfg.algorithm_name!r} {cfg.options}): {why}")


registry.on_replace(coverage_points.cache_clear)
registry.on_replace(_state_shapes.cache_clear)
