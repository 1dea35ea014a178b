"""One generation as a pure function of explicit state, and a whole run as a scan of it."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mqd_jax import archive as archive_lib
from mqd_jax import coverage, diagnostics, model, repertoire, selection, variation
from mqd_jax import filter as model_filter
from mqd_jax.config import Config, Params, check_params
from mqd_jax.task import Task, check_outputs

# Nearest pre-generation skills precomputed per candidate (see repertoire.py).
_NUM_NEAR = 4
# A generation's metrics (scalars; see `run_mqd`) and their dtypes: what a skipped generation reports (zeros)
# without tracing a generation to find out.
METRICS = {
    "coverage": jnp.float32, "mean_quality": jnp.float32, "repertoire_size": jnp.int32,
    "num_evaluations": jnp.int32, "evaluations": jnp.int32, "added": jnp.int32, "replaced": jnp.int32,
    "rejected": jnp.int32, "dropped_full": jnp.int32, "invalid": jnp.int32, "out_of_range": jnp.int32,
    "out_of_box": jnp.int32, "discarded": jnp.int32, "model_loss": jnp.float32, "prediction_error": jnp.float32,
}


@struct.dataclass
class State:
    """Everything a run carries from one generation to the next.

    Attributes:
      repertoire: the skills found so far (capacity C).
      archive: skills rejected or replaced (ring buffer of size A).
      coverage: coverage grid of the repertoire's disks.
      model: M-QD's forward model (initialised, never trained, for QD and RANDOM).
      key: PRNG key for the next generation.
      generation: int32, generations done.
      num_evaluations: int32, rollouts evaluated so far.
    """

    repertoire: repertoire.Repertoire
    archive: archive_lib.Archive
    coverage: coverage.CoverageGrid
    model: model.ModelState
    key: jax.Array
    generation: jax.Array
    num_evaluations: jax.Array


def get_task(cfg: Config) -> Task:
    """The task `cfg.task` names (from the `envs` registry)."""
    from envs import make

    if cfg.physics_backend == "auto":
        return make(cfg.task)
    return make(cfg.task, backend=cfg.physics_backend)


@functools.cache
def _reachable(cfg: Config) -> np.ndarray:
    """[G, G] reachable cells of the coverage grid, computed once per config."""
    task = get_task(cfg)
    centres = coverage.cell_centres(np.asarray(task.behavior_low), np.asarray(task.behavior_high),
                                    cfg.coverage_resolution)
    return task.reachable(centres)


def init(key: jax.Array, cfg: Config) -> State:
    """The state before the first generation: empty repertoire and archive, random model. Jitted.

    Raises ValueError if the task's `evaluate` breaks the task protocol's shapes.
    """
    check_outputs(get_task(cfg), cfg.task, cfg.population_size)
    return _init(key, cfg)


@functools.partial(jax.jit, static_argnames="cfg")
def _init(key: jax.Array, cfg: Config) -> State:
    # One compiled program rather than a few dozen eager operations: a second start loads it from the cache.
    task = get_task(cfg)
    n, d = task.action_dim, task.behavior_dim
    key, k_model = jax.random.split(key)
    return State(
        repertoire=repertoire.Repertoire.empty(cfg.capacity, n, d, cfg.neighbours),
        archive=archive_lib.Archive.empty(cfg.archive_capacity, n, d),
        coverage=coverage.empty(np.asarray(task.behavior_low), np.asarray(task.behavior_high),
                                _reachable(cfg), cfg.t_dist),
        model=model.init(k_model, cfg, task),
        key=key,
        generation=jnp.int32(0),
        num_evaluations=jnp.int32(0),
    )


@functools.cache
def _state_shapes(cfg: Config) -> State:
    """The shapes and dtypes of a state of `cfg` (abstract: nothing runs)."""
    return jax.eval_shape(lambda k: init(k, cfg), jax.ShapeDtypeStruct((2,), jnp.uint32))


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
                         f"hidden_size {cfg.hidden_size}): {why}")


def _candidates(key: jax.Array, state: State, cfg: Config, params: Params, task: Task, num: int) -> jax.Array:
    """[num, n] actions: uniform for RANDOM and while the repertoire is empty, else iso+line children."""
    low, high = jnp.asarray(task.action_low, jnp.float32), jnp.asarray(task.action_high, jnp.float32)
    k_uniform, k_parents, k_vary = jax.random.split(key, 3)
    fresh = variation.uniform(k_uniform, num, low, high)
    if cfg.algorithm == "random":
        return fresh
    rep = state.repertoire
    parents = selection.sample_parents(k_parents, rep.novelty, rep.valid, 2 * num)
    x = rep.actions[parents].reshape(2, num, -1)
    children = variation.iso_line(k_vary, x[0], x[1], params.iso_sigma, params.line_sigma, low, high)
    return jnp.where(rep.count > 0, children, fresh)


@struct.dataclass
class Candidates:
    """A generation's candidates, as `ask` hands them to an evaluator (P = population size).

    Attributes:
      actions: [P, n] actions.
      evaluate: [P] bool, the candidates to roll out (M-QD's filter; all for QD
        and RANDOM). The others' results are ignored.
      key: PRNG key for the rollouts (for stochastic tasks).
      pred_behaviors: [P, d] the model's predicted behaviors (M-QD), else NaN.
      discarded: int32, candidates the model turned down this generation.
    """

    actions: jax.Array
    evaluate: jax.Array
    key: jax.Array
    pred_behaviors: jax.Array
    discarded: jax.Array


def _checked(state: State, cfg: Config, params: Params | None) -> Params:
    """The checks every entry point makes before tracing (the state fits `cfg`, concrete params are valid); the
    params to pass on.

    `None` becomes `cfg.params()`, passed as arguments like any other values: one compiled program serves the
    config's own values and others, and XLA cannot fold them in as constants (which would round differently).
    """
    check_state(state, cfg)
    if params is None:
        return cfg.params()
    check_params(params, cfg)
    return params


def ask(state: State, cfg: Config, params: Params | None = None) -> Candidates:
    """Variation and, for M-QD after warm-up, the model's filter (Algorithm 1).

    Uses `state.key` and does not advance it: `tell` does. Pure and jitted.
    Raises ValueError for a state of another config or invalid concrete params.
    """
    return _ask(state, cfg, _checked(state, cfg, params))


@functools.partial(jax.jit, static_argnames="cfg")
def _ask(state: State, cfg: Config, params: Params) -> Candidates:
    task, pop = get_task(cfg), cfg.population_size
    _, k_cand, k_eval, _ = jax.random.split(state.key, 4)
    if cfg.algorithm != "mqd":
        actions = _candidates(k_cand, state, cfg, params, task, pop)
        return Candidates(actions, jnp.ones(pop, bool), k_eval, jnp.full((pop, task.behavior_dim), jnp.nan),
                          jnp.int32(0))
    warm_up = state.num_evaluations < cfg.warmup_samples
    pool = _candidates(k_cand, state, cfg, params, task, pop * cfg.pool_factor if cfg.budgeted else pop)
    pred_b, pred_q = model.predict(state.model, pool, cfg, task)
    novelty, improvement = model_filter.predicted_scores(pred_b, pred_q, state.repertoire, cfg.k)
    if cfg.budgeted:
        # During warm-up the pool's first P candidates stand in for QD's.
        top = jnp.where(warm_up, jnp.arange(pop), model_filter.budgeted_order(novelty, improvement, params.t_nov)[:pop])
        discarded = jnp.where(warm_up, 0, pool.shape[0] - pop).astype(jnp.int32)
        return Candidates(pool[top], jnp.ones(pop, bool), k_eval, pred_b[top], discarded)
    evaluate = warm_up | model_filter.passes(novelty, improvement, params.t_nov, params.t_qua)
    return Candidates(pool, evaluate, k_eval, pred_b, pop - evaluate.sum(dtype=jnp.int32))


def _train(state: State, rep: repertoire.Repertoire, key: jax.Array, cfg: Config, params: Params,
           task: Task) -> tuple[model.ModelState, jax.Array]:
    """Trains M-QD's model once warm-up is over; the loss is NaN when it does not train."""
    if cfg.algorithm != "mqd":
        return state.model, jnp.float32(jnp.nan)
    due = (state.num_evaluations >= cfg.warmup_samples) & (rep.count > 0)
    return jax.lax.cond(due, lambda: model.train(state.model, key, rep, cfg, task, params.learning_rate),
                        lambda: (state.model, jnp.float32(jnp.nan)))


def _check_results(behaviors: jax.Array, qualities: jax.Array, valid: jax.Array, pop: int, d: int) -> None:
    shapes = {"behaviors": (behaviors.shape, (pop, d)), "qualities": (qualities.shape, (pop,)),
              "valid": (valid.shape, (pop,))}
    for name, (got, want) in shapes.items():
        if tuple(got) != want:
            raise ValueError(f"tell: {name} has shape {tuple(got)}; expected {want} (one row per candidate)")
    if not jnp.issubdtype(valid.dtype, jnp.bool_):
        raise ValueError(f"tell: valid has dtype {valid.dtype}; expected bool")


def tell(state: State, candidates: Candidates, behaviors: jax.Array, qualities: jax.Array, valid: jax.Array,
         cfg: Config, params: Params | None = None) -> tuple[State, dict[str, jax.Array]]:
    """Insertion, archive, coverage, novelty and model training for evaluated candidates. Jitted.

    Args:
      state: the state `ask` was called with.
      candidates: what `ask` returned.
      behaviors: [P, d], qualities: [P], valid: [P] bool: the rollouts' results
        (arrays or nested lists); rows that `candidates.evaluate` leaves out are
        ignored (any value).

    Returns:
      The next state (key advanced) and the generation's metrics (see `run_mqd`).
    """
    params = _checked(state, cfg, params)
    behaviors, qualities, valid = (jnp.asarray(x) for x in (behaviors, qualities, valid))
    _check_results(behaviors, qualities, valid, cfg.population_size, get_task(cfg).behavior_dim)
    return _tell(state, candidates, behaviors, qualities, valid, cfg, params)


@functools.partial(jax.jit, static_argnames="cfg")
def _tell(state: State, candidates: Candidates, behaviors: jax.Array, qualities: jax.Array, valid: jax.Array,
          cfg: Config, params: Params) -> tuple[State, dict[str, jax.Array]]:
    task, pop = get_task(cfg), cfg.population_size
    key, _, _, k_train = jax.random.split(state.key, 4)
    actions = candidates.actions
    ok = candidates.evaluate & valid & jnp.isfinite(behaviors).all(axis=1) & jnp.isfinite(qualities)
    behaviors = jnp.where(ok[:, None], behaviors, 0.0).astype(jnp.float32)
    qualities = jnp.where(ok, qualities, 0.0).astype(jnp.float32)

    before = state.repertoire
    rep, ins = repertoire.insert(before, actions, behaviors, qualities, ok, params.t_dist, cfg.k, _NUM_NEAR,
                                 chunk=32)

    # Archive: the candidate itself, or the skill it replaced.
    from_old = ins.victim_slot >= 0
    from_cand = ins.victim_candidate >= 0
    src = jnp.where(from_cand, ins.victim_candidate, jnp.arange(pop))
    slot_old = jnp.maximum(ins.victim_slot, 0)
    pick = lambda old, cand: jnp.where(  # noqa: E731
        from_old.reshape((-1,) + (1,) * (cand.ndim - 1)), old[slot_old], cand[src])
    arch = archive_lib.push(state.archive, pick(before.actions, actions), pick(before.behaviors, behaviors),
                            pick(before.qualities, qualities), ins.archived)

    # Unstamp the replaced skills' disks and stamp the new skills' disks.
    grid = coverage.stamp(
        state.coverage, jnp.concatenate([before.behaviors[slot_old], behaviors]),
        jnp.concatenate([-from_old.astype(jnp.int32), ins.alive.astype(jnp.int32)]), params.t_dist)

    evaluations = candidates.evaluate.sum(dtype=jnp.int32)
    state = state.replace(num_evaluations=state.num_evaluations + evaluations)
    # Prediction error on this generation's rollouts, before they train the model.
    sq_err = jnp.where(ok[:, None], (candidates.pred_behaviors - behaviors) ** 2, 0.0).sum()
    prediction_error = jnp.where(ok.any(), sq_err / (ok.sum() * task.behavior_dim), jnp.nan)
    trained, loss = _train(state, rep, k_train, cfg, params, task)
    state = State(repertoire=rep, archive=arch, coverage=grid, model=trained, key=key,
                  generation=state.generation + 1, num_evaluations=state.num_evaluations)
    count = lambda s: (ins.status == s).sum(dtype=jnp.int32)  # noqa: E731
    q_low, q_high = task.quality_range
    outside_box = ((behaviors < jnp.asarray(task.behavior_low, jnp.float32))
                   | (behaviors > jnp.asarray(task.behavior_high, jnp.float32))).any(axis=1)
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
        "invalid": (candidates.evaluate & ~ok).sum(dtype=jnp.int32),
        "out_of_range": (ok & ((qualities < q_low) | (qualities > q_high))).sum(dtype=jnp.int32),
        "out_of_box": (ok & outside_box).sum(dtype=jnp.int32),
        "discarded": candidates.discarded,
        "model_loss": loss,
        "prediction_error": prediction_error,
    }
    return state, metrics


def generation(state: State, cfg: Config, params: Params) -> tuple[State, dict[str, jax.Array]]:
    """One generation: exactly `ask`, the task's rollouts, `tell`."""
    candidates = ask(state, cfg, params)
    behaviors, qualities, valid = get_task(cfg).evaluate_masked(candidates.actions, candidates.key,
                                                                candidates.evaluate)
    return tell(state, candidates, behaviors, qualities, valid, cfg, params)


def run_generations(state: State, cfg: Config, params: Params, num: int,
                    todo: jax.Array | None = None) -> tuple[State, dict[str, jax.Array]]:
    """`num` generations as one `lax.scan`; metrics are stacked, shape (num,).

    With `todo` (an int32, may be traced) only the first `todo` generations run
    and the rest leave the state as it is (their metrics are zeros): one
    compiled program of `num` generations then also serves a shorter last chunk.
    """
    if todo is None:
        return jax.lax.scan(lambda s, _: generation(s, cfg, params), state, None, length=num)
    skipped = {name: jnp.zeros((), dtype) for name, dtype in METRICS.items()}
    return jax.lax.scan(lambda s, i: jax.lax.cond(i < todo, lambda: generation(s, cfg, params), lambda: (s, skipped)),
                        state, jnp.arange(num))


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
      num_evaluations (cumulative), evaluations (rollouts this generation),
      added, replaced, rejected, dropped_full, invalid (evaluated, but failed
      or non-finite), discarded (turned down by M-QD's model), model_loss
      (mean training loss of the generation's mini-batches) and
      prediction_error (behavior MSE in real units of the model's predictions
      on this generation's valid rollouts, before training on them; these two
      are NaN where they do not apply: QD, RANDOM, no training or no valid
      rollout), out_of_range (valid rollouts whose quality lies outside
      `Task.quality_range`) and out_of_box (valid rollouts whose behavior lies
      outside the behavior box).

    Raises ValueError for invalid concrete `params` (NaN, infinite, out of
    range). Called with concrete arguments it waits for the run and warns
    (`diagnostics.RunWarning`, once per problem, with counts) about dropped
    niches, qualities outside the task's quality range, behaviors outside
    the behavior box, and runs whose every rollout was invalid.
    """
    if params is None:
        params = cfg.params()  # as arguments: the same compiled run for the config's values and others
    check_params(params, cfg)
    state, metrics = _run_mqd(key, cfg, params)
    if not any(isinstance(m, jax.core.Tracer) for m in metrics.values()):  # concrete: not inside a jit or vmap
        diagnostics.warn(jax.device_get(metrics), cfg, get_task(cfg))
    return state, metrics


@functools.partial(jax.jit, static_argnames="cfg")
def _run_mqd(key: jax.Array, cfg: Config, params: Params) -> tuple[State, dict[str, jax.Array]]:
    return run_generations(init(key, cfg), cfg, params, cfg.max_generations)
