"""One generation as a pure function of explicit state, and a whole run as a scan of it."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mqd_jax import archive as archive_lib
from mqd_jax import coverage, repertoire, selection, variation
from mqd_jax.config import Config, Params
from mqd_jax.task import Task

# Nearest pre-generation skills precomputed per candidate (see repertoire.py).
_NUM_NEAR = 4


@struct.dataclass
class State:
    """Everything a run carries from one generation to the next.

    Attributes:
      repertoire: the skills found so far (capacity C).
      archive: skills rejected or replaced (ring buffer of size A).
      coverage: coverage grid of the repertoire's disks.
      key: PRNG key for the next generation.
      generation: int32, generations done.
      num_evaluations: int32, rollouts evaluated so far.
    """

    repertoire: repertoire.Repertoire
    archive: archive_lib.Archive
    coverage: coverage.CoverageGrid
    key: jax.Array
    generation: jax.Array
    num_evaluations: jax.Array


def get_task(cfg: Config) -> Task:
    """The task `cfg.task` names (from the `envs` registry)."""
    from envs import make

    return make(cfg.task)


@functools.cache
def _reachable(cfg: Config) -> np.ndarray:
    """[G, G] reachable cells of the coverage grid, computed once per config."""
    task = get_task(cfg)
    centres = coverage.cell_centres(np.asarray(task.behavior_low), np.asarray(task.behavior_high),
                                    cfg.coverage_resolution)
    return task.reachable(centres)


def init(key: jax.Array, cfg: Config) -> State:
    """The state before the first generation: empty repertoire and archive."""
    task = get_task(cfg)
    n, d = task.action_dim, task.behavior_dim
    return State(
        repertoire=repertoire.Repertoire.empty(cfg.capacity, n, d, cfg.neighbours),
        archive=archive_lib.Archive.empty(cfg.archive_capacity, n, d),
        coverage=coverage.empty(np.asarray(task.behavior_low), np.asarray(task.behavior_high),
                                _reachable(cfg), cfg.t_dist),
        key=key,
        generation=jnp.int32(0),
        num_evaluations=jnp.int32(0),
    )


def _candidates(key: jax.Array, state: State, cfg: Config, params: Params, task: Task) -> jax.Array:
    """[P, n] actions: uniform for RANDOM and while the repertoire is empty, else iso+line children."""
    low, high = jnp.asarray(task.action_low, jnp.float32), jnp.asarray(task.action_high, jnp.float32)
    k_uniform, k_parents, k_vary = jax.random.split(key, 3)
    fresh = variation.uniform(k_uniform, cfg.population_size, low, high)
    if cfg.algorithm == "random":
        return fresh
    rep = state.repertoire
    parents = selection.sample_parents(k_parents, rep.novelty, rep.valid, 2 * cfg.population_size)
    x = rep.actions[parents].reshape(2, cfg.population_size, -1)
    children = variation.iso_line(k_vary, x[0], x[1], params.iso_sigma, params.line_sigma, low, high)
    return jnp.where(rep.count > 0, children, fresh)


def generation(state: State, cfg: Config, params: Params) -> tuple[State, dict[str, jax.Array]]:
    """One generation: variation, rollouts, sequential insertion, novelty and metrics."""
    task = get_task(cfg)
    key, k_cand, k_eval = jax.random.split(state.key, 3)
    actions = _candidates(k_cand, state, cfg, params, task)
    behaviors, qualities, valid = task.evaluate(actions, k_eval)
    ok = valid & jnp.isfinite(behaviors).all(axis=1) & jnp.isfinite(qualities)
    behaviors = jnp.where(ok[:, None], behaviors, 0.0)
    qualities = jnp.where(ok, qualities, 0.0)

    before = state.repertoire
    rep, ins = repertoire.insert(before, actions, behaviors, qualities, ok, params.t_dist, cfg.k, _NUM_NEAR,
                                 chunk=32)

    # Archive: the candidate itself, or the skill it replaced.
    from_old = ins.victim_slot >= 0
    from_cand = ins.victim_candidate >= 0
    src = jnp.where(from_cand, ins.victim_candidate, jnp.arange(cfg.population_size))
    slot_old = jnp.maximum(ins.victim_slot, 0)
    pick = lambda old, cand: jnp.where(  # noqa: E731
        from_old.reshape((-1,) + (1,) * (cand.ndim - 1)), old[slot_old], cand[src])
    arch = archive_lib.push(state.archive, pick(before.actions, actions), pick(before.behaviors, behaviors),
                            pick(before.qualities, qualities), ins.archived)

    # Unstamp the replaced skills' disks and stamp the new skills' disks.
    grid = coverage.stamp(
        state.coverage, jnp.concatenate([before.behaviors[slot_old], behaviors]),
        jnp.concatenate([-from_old.astype(jnp.int32), ins.alive.astype(jnp.int32)]), params.t_dist)

    evaluations = jnp.int32(cfg.population_size)
    state = State(repertoire=rep, archive=arch, coverage=grid, key=key, generation=state.generation + 1,
                  num_evaluations=state.num_evaluations + evaluations)
    count = lambda s: (ins.status == s).sum(dtype=jnp.int32)  # noqa: E731
    metrics = {
        "coverage": coverage.fraction(grid),
        "mean_quality": jnp.where(rep.valid, rep.qualities, 0.0).sum() / jnp.maximum(rep.count, 1),
        "repertoire_size": rep.count,
        "num_evaluations": state.num_evaluations,
        "evaluations": evaluations,
        "added": count(repertoire.ADDED),
        "replaced": count(repertoire.REPLACED),
        "rejected": count(repertoire.REJECTED),
        "dropped_full": count(repertoire.DROPPED_FULL),
        "invalid": (~ok).sum(dtype=jnp.int32),
    }
    return state, metrics


def run_generations(state: State, cfg: Config, params: Params, num: int) -> tuple[State, dict[str, jax.Array]]:
    """`num` generations as one `lax.scan`; metrics are stacked, shape (num,)."""
    return jax.lax.scan(lambda s, _: generation(s, cfg, params), state, None, length=num)


@functools.partial(jax.jit, static_argnames="cfg")
def run_mqd(key: jax.Array, cfg: Config, params: Params | None = None) -> tuple[State, dict[str, jax.Array]]:
    """A whole run: `cfg.max_generations` generations from an empty repertoire.

    Args:
      key: PRNG key; the same key and config give the same result on a backend.
      cfg: static configuration.
      params: traced thresholds and rates; defaults to `cfg.params()`. Pass
        these to `jax.vmap` a single compiled run over, say, t_nov.

    Returns:
      The final state and a dict of per-generation metrics, each of shape
      (max_generations,): coverage, mean_quality, repertoire_size,
      num_evaluations (cumulative), evaluations, added, replaced, rejected,
      dropped_full, invalid.
    """
    params = cfg.params() if params is None else params
    return run_generations(init(key, cfg), cfg, params, cfg.max_generations)
