"""One generation as a pure function of explicit state (`mqd_jax.core.state`), and a whole run as a scan of it.

A run searches with an emitter (`mqd_jax.core.emitter`; a preset the config names,
or any composition) on a task, in named stages:

    propose -> evaluate -> insert -> archive -> coverage -> emitter update -> metrics

`ask` is the first stage and `tell` the stages after the rollouts, so that an
evaluator outside JAX can sit between them; `generation` is all of them.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import archive as archive_lib
from mqd_jax.core import checks, coverage, diagnostics, pytree, repertoire
from mqd_jax.core.config import Config, check_params
from mqd_jax.core.emitter import Evaluated, Proposal
from mqd_jax.core.params import Params
from mqd_jax.core.repertoire import AddStatus
from mqd_jax.core.state import State, check_state, get_task, init, kept_features, metric_dtypes, stage
from mqd_jax.core.task import Task


@pytree.dataclass
class Candidates:
    """A generation's candidates, as `ask` hands them to an evaluator (P = population size).

    Attributes:
      actions: [P, n] actions.
      rollout: [P] bool, the candidates to roll out (M-QD: those its model
        chose); the others' results are ignored.
      key: PRNG key for the rollouts (for stochastic tasks).
      info: the emitter's data about its proposal, handed back to its update.
      generation: int32, the generation of the state they were asked for: `tell`
        refuses them for a state of another generation.
      features: [P, f] the task's features of the actions where the repertoire keeps them
        (`Repertoire.features`; f = 0 otherwise).
    """

    actions: jax.Array
    rollout: jax.Array
    key: jax.Array
    info: Any
    generation: jax.Array
    features: jax.Array


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
    """The propose stage: the emitter's candidates for this generation. Pure and jitted.

    Uses `state.key` and does not advance it: `tell` does. Raises ValueError
    for a state of another config, invalid concrete params, or an emitter
    whose proposal is not shaped actions [P, n], rollout [P] bool; called with
    concrete arguments it waits for the candidates, and a part that breaks its
    contract under `checks=True` raises `PartFailed` here, one line.
    """
    params = _checked(state, cfg, params)
    return _settled(lambda: _ask(state, cfg, params))


def _settled(compute: Callable[[], Any]) -> Any:
    """compute()'s results, waited for where they are concrete (not inside a jit or vmap, as `generation` calls
    `ask` and `tell`), so that a `PartFailed` raised as the program runs is raised here as itself
    (`checks.part_failures`), not later where its results are first read."""
    with checks.part_failures():
        out = compute()
        if _concrete(out):
            jax.block_until_ready(out)
    return out


def _concrete(tree: Any) -> bool:
    """Whether `tree` holds no tracer (its function was called outside a jit or vmap)."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(tree))


@functools.partial(jax.jit, static_argnames="cfg")
def _ask(state: State, cfg: Config, params: Params) -> Candidates:
    return _propose(state, cfg, params)


@stage("emit")
def _propose(state: State, cfg: Config, params: Params) -> Candidates:
    """Stage propose: `population_size` candidates from the emitter, and the key of their rollouts."""
    task, pop = get_task(cfg), cfg.population_size
    _, k_propose, k_rollout, _ = jax.random.split(state.key, 4)
    emitter = cfg.emitter
    proposal = emitter.propose(k_propose, state.emitter, state.repertoire, task, params, pop)
    shapes = (jnp.shape(proposal.actions), jnp.shape(proposal.rollout), jnp.result_type(proposal.rollout))
    if shapes != ((pop, task.action_dim), (pop,), jnp.bool_):
        raise ValueError(f"{emitter!r}.propose returned actions {shapes[0]} and rollout {shapes[1]} {shapes[2]}; "
                         f"expected ({pop}, {task.action_dim}) and ({pop},) bool")
    actions = proposal.actions.astype(jnp.float32)
    kept = kept_features(cfg)
    features = jnp.zeros((pop, 0), jnp.float32)
    if kept:
        features = task.features(actions) if proposal.features is None else proposal.features
        if jnp.shape(features) != (pop, kept):
            raise ValueError(f"{emitter!r}.propose returned features {jnp.shape(features)}; expected ({pop}, {kept})")
    return Candidates(actions, proposal.rollout, k_rollout, proposal.info, state.generation,
                      jnp.asarray(features, jnp.float32))


@stage("evaluate")
def _evaluate(candidates: Candidates, task: Task) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Stage evaluate: the task's rollouts of the candidates to roll out: behaviors, qualities, valid and the
    auxiliary outputs ([P, 0] for a task without them)."""
    return task.evaluate_with_auxiliary(candidates.actions, candidates.key, candidates.rollout)


def _usable(candidates: Candidates, behaviors: jax.Array, qualities: jax.Array,
            valid: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Behaviors [P, d] and qualities [P] as float32, zero where not usable, and usable [P]: rolled out,
    valid and finite."""
    usable = candidates.rollout & valid & jnp.isfinite(behaviors).all(axis=1) & jnp.isfinite(qualities)
    behaviors = jnp.where(usable[:, None], behaviors, 0.0).astype(jnp.float32)
    return behaviors, jnp.where(usable, qualities, 0.0).astype(jnp.float32), usable


@stage("insert")
def _insert(rep: repertoire.Repertoire, actions: jax.Array, behaviors: jax.Array, qualities: jax.Array,
            usable: jax.Array, cfg: Config, params: Params,
            features: jax.Array) -> tuple[repertoire.Repertoire, repertoire.Insertion]:
    """Stage insert: the paper's sequential insertion rule (computed in data-parallel rounds); novelty brought up
    to date."""
    return repertoire.insert(rep, actions, behaviors, qualities, usable, params.t_dist, cfg.k, repertoire.NUM_NEAR,
                             chunk=32, features=features)


@stage("archive")
def _archive(arch: archive_lib.Archive, before: repertoire.Repertoire, actions: jax.Array, evaluated: Evaluated,
             ins: repertoire.Insertion) -> archive_lib.Archive:
    """Stage archive: what each candidate's step put out of the repertoire (itself, or the skill it replaced)."""
    from_old = ins.victim_slot >= 0
    src = jnp.where(ins.victim_candidate >= 0, ins.victim_candidate, jnp.arange(from_old.shape[0]))
    slot_old = jnp.maximum(ins.victim_slot, 0)
    pick = lambda old, cand: jnp.where(  # noqa: E731
        from_old.reshape((-1,) + (1,) * (cand.ndim - 1)), old[slot_old], cand[src])
    return archive_lib.push(arch, pick(before.actions, actions), pick(before.behaviors, evaluated.behaviors),
                            pick(before.qualities, evaluated.qualities), ins.archived)


@stage("coverage")
def _cover(grid: coverage.Grid | coverage.Samples, before: repertoire.Repertoire, evaluated: Evaluated,
           ins: repertoire.Insertion, t_dist: jax.Array) -> coverage.Grid | coverage.Samples:
    """Stage coverage: unstamps the replaced skills' balls and stamps the new skills' balls."""
    from_old = ins.victim_slot >= 0
    return coverage.stamp(
        grid, jnp.concatenate([before.behaviors[jnp.maximum(ins.victim_slot, 0)], evaluated.behaviors]),
        jnp.concatenate([-from_old.astype(jnp.int32), ins.alive.astype(jnp.int32)]), t_dist)


@stage("update")
def _update_emitter(key: jax.Array, state: State, candidates: Candidates, evaluated: Evaluated,
                    rep: repertoire.Repertoire, cfg: Config, params: Params) -> tuple[Any, dict[str, jax.Array]]:
    """Stage emitter update: the emitter learns from the results; its metrics, checked against its `metrics()`."""
    emitter = cfg.emitter
    proposal = Proposal(candidates.actions, candidates.rollout, candidates.info,
                        features=candidates.features if candidates.features.shape[1] else None)
    emitter_state, metrics = emitter.update(key, state.emitter, proposal, evaluated, rep, get_task(cfg), params)
    declared = emitter.metrics()
    if set(metrics) != set(declared):
        raise ValueError(f"{emitter!r}.update returned the metrics {sorted(metrics)}, but its metrics() declares "
                         f"{sorted(declared)}")
    return emitter_state, {name: jnp.asarray(metrics[name], dtype) for name, dtype in declared.items()}


@stage("metrics")
def _metrics(state: State, candidates: Candidates, evaluated: Evaluated, task: Task,
             rounds: jax.Array) -> dict[str, jax.Array]:
    """Stage metrics: the engine's metrics of the generation that made `state` (see `run_mqd`); `rounds`: the
    insertion's."""
    rep, usable = state.repertoire, evaluated.usable
    count = lambda status: (evaluated.status == status).sum(dtype=jnp.int32)  # noqa: E731
    q_low, q_high = task.quality_range
    outside_box = ((evaluated.behaviors < jnp.asarray(task.behavior_low, jnp.float32))
                   | (evaluated.behaviors > jnp.asarray(task.behavior_high, jnp.float32))).any(axis=1)
    return {
        "coverage": coverage.fraction(state.coverage),
        "mean_quality": jnp.where(rep.valid, rep.qualities, 0.0).sum() / jnp.maximum(rep.count, 1),
        "max_quality": jnp.where(rep.valid, rep.qualities, q_low).max(),
        "qd_score": jnp.where(rep.valid, rep.qualities - q_low, 0.0).sum(),
        "repertoire_size": rep.count,
        "num_evaluations": state.num_evaluations,
        "evaluations": candidates.rollout.sum(dtype=jnp.int32),
        "added": count(AddStatus.ADDED),
        "replaced": count(AddStatus.REPLACED),
        "rejected": count(AddStatus.REJECTED),
        "dropped_full": count(AddStatus.DROPPED_FULL),
        "invalid": (candidates.rollout & ~usable).sum(dtype=jnp.int32),
        "out_of_range": (usable & ((evaluated.qualities < q_low) | (evaluated.qualities > q_high))).sum(
            dtype=jnp.int32),
        "out_of_box": (usable & outside_box).sum(dtype=jnp.int32),
        "insertion_rounds": rounds,
    }


def _check_results(behaviors: jax.Array, qualities: jax.Array, valid: jax.Array, auxiliary: jax.Array | None,
                   pop: int, task: Task, task_name: str) -> jax.Array:
    """Raises ValueError unless the results fit the population and the task; returns the auxiliary outputs
    ([P, 0] for a task without them)."""
    names = task.auxiliary
    if auxiliary is None:
        if names:
            raise ValueError(f"tell: task {task_name!r} returns auxiliary outputs {names}: pass auxiliary= "
                             f"[{pop}, {len(names)}], the fourth output of its evaluate_with_auxiliary")
        auxiliary = jnp.zeros((pop, 0), jnp.float32)
    shapes = {"behaviors": (behaviors.shape, (pop, task.behavior_dim)), "qualities": (qualities.shape, (pop,)),
              "valid": (valid.shape, (pop,)), "auxiliary": (jnp.shape(auxiliary), (pop, len(names)))}
    for name, (got, want) in shapes.items():
        if tuple(got) != want:
            raise ValueError(f"tell: {name} has shape {tuple(got)}; expected {want} (one row per candidate)")
    if not jnp.issubdtype(valid.dtype, jnp.bool_):
        raise ValueError(f"tell: valid has dtype {valid.dtype}; expected bool")
    return jnp.asarray(auxiliary)


def tell(state: State, candidates: Candidates, behaviors: jax.Array, qualities: jax.Array, valid: jax.Array,
         cfg: Config, params: Params | None = None,
         auxiliary: jax.Array | None = None) -> tuple[State, dict[str, jax.Array]]:
    """The stages after the rollouts: insert, archive, coverage, emitter update, metrics. Jitted.

    Args:
      state: the state `ask` was called with.
      candidates: what `ask` returned (refused, with a ValueError, for a state of
        another generation: candidates of an older `ask`).
      behaviors: [P, d], qualities: [P], valid: [P] bool: the rollouts' results
        (arrays or nested lists); rows that `candidates.rollout` leaves out are
        ignored (any value).
      auxiliary: [P, m] the task's auxiliary outputs (`Task.auxiliary`), required
        for a task that names some; None for one that does not.

    Returns:
      The next state (key advanced) and the generation's metrics (see `run_mqd`);
      called with concrete arguments it waits for them, as `ask` does.
    """
    params = _checked(state, cfg, params)
    asked, now = candidates.generation, state.generation
    if _concrete((asked, now)) and int(asked) != int(now):
        raise ValueError(f"tell: these candidates were asked at generation {int(asked)}, the state is at generation "
                         f"{int(now)}: tell each ask's candidates once, with the state ask was given, then ask again")
    behaviors, qualities, valid = (jnp.asarray(x) for x in (behaviors, qualities, valid))
    auxiliary = _check_results(behaviors, qualities, valid, auxiliary, cfg.population_size, get_task(cfg),
                               cfg.task_name)
    return _settled(lambda: _tell(state, candidates, behaviors, qualities, valid, auxiliary, cfg, params))


@functools.partial(jax.jit, static_argnames="cfg")
def _tell(state: State, candidates: Candidates, behaviors: jax.Array, qualities: jax.Array, valid: jax.Array,
          auxiliary: jax.Array, cfg: Config, params: Params) -> tuple[State, dict[str, jax.Array]]:
    key, _, _, k_update = jax.random.split(state.key, 4)
    behaviors, qualities, usable = _usable(candidates, behaviors, qualities, valid)
    rep, ins = _insert(state.repertoire, candidates.actions, behaviors, qualities, usable, cfg, params,
                       candidates.features)
    auxiliary = jnp.where(usable[:, None], auxiliary, 0.0).astype(jnp.float32)
    evaluated = Evaluated(behaviors, qualities, usable, ins.status, auxiliary)
    emitter_state, emitter_metrics = _update_emitter(k_update, state, candidates, evaluated, rep, cfg, params)
    new = State(repertoire=rep, archive=_archive(state.archive, state.repertoire, candidates.actions, evaluated, ins),
                coverage=_cover(state.coverage, state.repertoire, evaluated, ins, params.t_dist),
                emitter=emitter_state, key=key, generation=state.generation + 1,
                num_evaluations=state.num_evaluations + candidates.rollout.sum(dtype=jnp.int32))
    return new, {**_metrics(new, candidates, evaluated, get_task(cfg), ins.rounds), **emitter_metrics}


def generation(state: State, cfg: Config, params: Params) -> tuple[State, dict[str, jax.Array]]:
    """One generation: exactly `ask`, the task's rollouts, `tell`."""
    candidates = ask(state, cfg, params)
    behaviors, qualities, valid, auxiliary = _evaluate(candidates, get_task(cfg))
    return tell(state, candidates, behaviors, qualities, valid, cfg, params, auxiliary)


def run_generations(state: State, cfg: Config, params: Params, num: int,
                    todo: jax.Array | None = None) -> tuple[State, dict[str, jax.Array]]:
    """`num` generations as one `lax.scan`; metrics are stacked, shape (num,).

    With `todo` (an int32, may be traced) only the first `todo` generations run
    and the rest leave the state as it is (their metrics are zeros): one
    compiled program of `num` generations then also serves a shorter last chunk.
    """
    if todo is None:
        return jax.lax.scan(lambda s, _: generation(s, cfg, params), state, None, length=num)
    skipped = {name: jnp.zeros((), dtype) for name, dtype in metric_dtypes(cfg).items()}
    return jax.lax.scan(lambda s, i: jax.lax.cond(i < todo, lambda: generation(s, cfg, params), lambda: (s, skipped)),
                        state, jnp.arange(num))


def run_mqd(key: jax.Array, cfg: Config, params: Params | None = None) -> tuple[State, dict[str, jax.Array]]:
    """A whole run: `cfg.max_generations` generations from an empty repertoire, with any emitter.

    The search is the emitter `cfg.algorithm` gives: a preset's name ("mqd",
    "qd", "random") or any `Emitter` composition (see `mqd_jax.core.emitter`).

    Args:
      key: PRNG key; the same key and config give the same result on a backend.
      cfg: static configuration.
      params: traced thresholds and rates; defaults to `cfg.params()`. Pass
        these to `jax.vmap` a single compiled run over, say, t_nov.

    Returns:
      The final state and a dict of per-generation metrics, each of shape
      (max_generations,): coverage, mean_quality, repertoire_size,
      num_evaluations (cumulative), evaluations (rollouts this generation),
      added, replaced, rejected, dropped_full (insertion's `AddStatus`
      counts), invalid (rolled out, but failed or non-finite), out_of_range
      (valid rollouts whose quality lies outside `Task.quality_range`) and
      out_of_box (valid rollouts whose behavior lies outside the behavior
      box); then the emitter's own (`Emitter.metrics`; M-QD's model emitter:
      discarded, model_loss, prediction_error).

    Raises ValueError for invalid concrete `params` (NaN, infinite, out of
    range). Called with concrete arguments it waits for the run and warns
    (`diagnostics.RunWarning`, once per problem, with counts) about dropped
    niches, qualities outside the task's quality range, behaviors outside
    the behavior box, and runs whose every rollout was invalid.
    """
    if params is None:
        params = cfg.params()  # as arguments: the same compiled run for the config's values and others
    check_params(params, cfg)
    state, metrics = _settled(lambda: _run_mqd(key, cfg, params))
    if _concrete(metrics):
        diagnostics.warn(jax.device_get(metrics), cfg, get_task(cfg))
    return state, metrics


@functools.partial(jax.jit, static_argnames="cfg")
def _run_mqd(key: jax.Array, cfg: Config, params: Params) -> tuple[State, dict[str, jax.Array]]:
    return run_generations(init(key, cfg), cfg, params, cfg.max_generations)
