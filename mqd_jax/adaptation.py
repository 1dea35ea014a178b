"""Skill adaptation toward arbitrary goal behaviors (paper, "Adaptation of Skills").

For a goal b*, start from the repertoire skill nearest to it in behavior space,
(a_0, b_0), and step

    a_{j+1} = clip(a_j + lambda * pinv(J(a_j)) (b* - b_j)),   b_{j+1} = rollout(a_{j+1}),

until ||b* - b_j|| < t_dist or `steps` steps were made (Table II: lambda = `step_size` = 0.1, 10 steps).
Methods:

* "nearest": no step; the nearest skill itself.
* "linear" (the paper's baseline): J = B pinv(G), with G [n, K] the K nearest
  repertoire actions to a_j minus a_j (nearest in normalized action units, so
  that every action dimension counts alike) and B [d, K] their behaviors minus
  b_j. With K >= n and G of full rank this is the paper's B G^T (G G^T)^-1;
  with K < n (G G^T singular) it is the minimum-norm J with J G = B.
* "model": J is the Jacobian of the model's behavior prediction in real units
  at a_j, from `jax.jacfwd`.

Every goal runs in parallel; a goal that has stopped is masked out of the
remaining steps' rollouts. The result is the best iterate (lowest behavioral
error among a_0 and the evaluated a_j), so no method ends worse than
"nearest". A failed or non-finite rollout counts as a step and ends that
goal's adaptation.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import neighbours, pytree
from mqd_jax.core.checks import check_traced, is_int
from mqd_jax.core.config import Config
from mqd_jax.core.state import State, check_state, get_task
from mqd_jax.core.task import Task
from mqd_jax.surrogate import model

METHODS = ("nearest", "linear", "model")
# Table II: the step size lambda and the number of adaptation steps.
STEP_SIZE, STEPS = 0.1, 10


@pytree.dataclass
class Adapted:
    """The outcome for G goals.

    Attributes:
      actions: [G, n] the best action found for each goal.
      behaviors: [G, d] its behavior.
      errors: [G] behavioral error ||b* - behavior||.
      steps: [G] int32 adaptation steps made.
      evaluations: [G] int32 rollouts spent (one per step).
    """

    actions: jax.Array
    behaviors: jax.Array
    errors: jax.Array
    steps: jax.Array
    evaluations: jax.Array


Jacobian = Callable[[jax.Array, jax.Array], jax.Array]


def _linear_jacobian(state: State, cfg: Config, task: Task) -> Jacobian:
    """J [G, d, n] from the K repertoire skills nearest to each a_j in action space."""
    rep = state.repertoire

    def jacobian(a: jax.Array, b: jax.Array) -> jax.Array:
        d = neighbours.sq_dists(model.normalize_actions(a, task), model.normalize_actions(rep.actions, task))
        found, idx = neighbours.k_smallest(jnp.where(rep.valid[None], d, jnp.inf), cfg.k)
        keep = jnp.isfinite(found)[..., None]
        g = jnp.where(keep, rep.actions[jnp.maximum(idx, 0)] - a[:, None], 0.0)  # [G, K, n] = G^T
        bb = jnp.where(keep, rep.behaviors[jnp.maximum(idx, 0)] - b[:, None], 0.0)  # [G, K, d] = B^T
        return jnp.einsum("gkd,gkn->gdn", bb, jnp.linalg.pinv(jnp.swapaxes(g, 1, 2)))

    return jacobian


def _model_jacobian(state: State, cfg: Config, task: Task) -> Jacobian:
    """J [G, d, n] of the model's behavior prediction (real units) at each a_j."""
    behavior, _ = cfg.emitter.forward_model(state.emitter, task)
    return lambda a, b: jax.vmap(jax.jacfwd(behavior))(a)


@functools.partial(jax.jit, static_argnames=("cfg", "method", "steps"))
def _adapt(state: State, goals: jax.Array, key: jax.Array, cfg: Config, method: str, step_size: jax.Array,
           steps: int, t_dist: jax.Array) -> Adapted:
    task = get_task(cfg)
    rep = state.repertoire
    nearest = jnp.argmin(jnp.where(rep.valid[None], neighbours.sq_dists(goals, rep.behaviors), jnp.inf), axis=1)
    a0, b0 = rep.actions[nearest], rep.behaviors[nearest]
    error = lambda b: jnp.linalg.norm(goals - b, axis=1)  # noqa: E731
    zeros = jnp.zeros(goals.shape[0], jnp.int32)
    if method == "nearest":
        return Adapted(a0, b0, error(b0), zeros, zeros)
    jacobian = (_linear_jacobian if method == "linear" else _model_jacobian)(state, cfg, task)
    low, high = jnp.asarray(task.action_low, jnp.float32), jnp.asarray(task.action_high, jnp.float32)

    def step(j: jax.Array, carry: tuple) -> tuple:
        a, b, (best_a, best_b, best_error), made, active = carry
        active = active & (error(b) >= t_dist)
        direction = jnp.einsum("gnd,gd->gn", jnp.linalg.pinv(jacobian(a, b)), goals - b)
        new_a = jnp.clip(a + step_size * direction, low, high)
        new_b, _, valid = task.evaluate_masked(new_a, jax.random.fold_in(key, j), active)
        ok = active & valid & jnp.isfinite(new_b).all(axis=1)
        a, b = jnp.where(ok[:, None], new_a, a), jnp.where(ok[:, None], new_b, b)
        better = ok & (error(b) < best_error)
        best = (jnp.where(better[:, None], a, best_a), jnp.where(better[:, None], b, best_b),
                jnp.where(better, error(b), best_error))
        return a, b, best, made + active, ok

    init = (a0, b0, (a0, b0, error(b0)), zeros, jnp.ones(goals.shape[0], bool))
    _, _, best, made, _ = jax.lax.fori_loop(0, steps, step, init)
    return Adapted(*best, steps=made, evaluations=made)


def _check(state: State, goals: jax.Array, cfg: Config, method: str, task: Task, step_size: float | jax.Array,
           steps: int, t_dist: float | jax.Array) -> None:
    if method not in METHODS:
        raise ValueError(f"method={method!r} is invalid: expected one of {METHODS}")
    if not (is_int(steps) and steps >= 0):
        raise ValueError(f"steps={steps!r} is invalid: expected an int >= 0")
    check_traced("adapt", "step_size", step_size, inclusive=False)
    check_traced("adapt", "t_dist", t_dist, inclusive=False)
    # Only what adaptation reads: t_dist may differ from the run's, and with it the coverage grid's stamp.
    check_state(state, cfg, batch=np.shape(state.repertoire.count), fields=("repertoire", "emitter"))
    found = cfg.emitter.forward_model(state.emitter, task)
    if method == "model" and found is None:
        raise ValueError(f"method 'model' needs a run whose emitter has a model (M-QD: a ModelEmitter, or a "
                         f"SideBySide with one), not {cfg.algorithm!r}: a QD or RANDOM run has no model")
    if goals.ndim < 2 or goals.shape[-1] != task.behavior_dim:
        raise ValueError(f"goals has shape {goals.shape}: expected (G, {task.behavior_dim}) for task "
                         f"{cfg.task_name!r}")
    if isinstance(state.repertoire.count, jax.core.Tracer):
        return
    if (np.asarray(state.repertoire.count) == 0).any():
        raise ValueError("the repertoire is empty: run the search first")
    # The model emitter fits its surrogate after every generation once warm-up is over.
    if method == "model" and not np.asarray(found[1]).all():
        raise ValueError("method 'model' needs a trained model: this state's model never trained "
                         "(an M-QD run that did not finish warm-up)")


def adapt(state: State, goals: jax.Array, key: jax.Array, cfg: Config, method: str,
          step_size: float | jax.Array = STEP_SIZE, steps: int = STEPS, t_dist: float | jax.Array | None = None
          ) -> Adapted:
    """Adapts the repertoire of `state` toward each goal behavior goals[G, d], in one jitted call.

    Args:
      state: a run's state (from `run_mqd` or `run_generations`); "model" needs
        the state of a run whose emitter has a model (`Emitter.forward_model`: a `ModelEmitter`, M-QD, or a
        `SideBySide` with one) that has trained.
      goals: [G, d] desired behaviors (anywhere; outside the behavior box too).
      key: PRNG key for the rollouts.
      cfg: the run's config (its task, k and emitter).
      method: "nearest", "linear" or "model".
      step_size: lambda, the step along pinv(J) (b* - b) (> 0; may be traced).
      steps: the most adaptation steps (rollouts) per goal (static).
      t_dist: a goal is reached within this distance (> 0; may be traced); default the run's `cfg.t_dist`.

    Raises ValueError for an unknown method, goals not shaped (G, d), an empty
    repertoire, an untrained model ("model"), a state of another config, and
    invalid concrete step_size, steps or t_dist.
    """
    task = get_task(cfg)
    goals = jnp.asarray(goals, jnp.float32)
    t_dist = cfg.t_dist if t_dist is None else t_dist
    _check(state, goals, cfg, method, task, step_size, steps, t_dist)
    if goals.ndim != 2:
        raise ValueError(f"goals has shape {goals.shape}: expected (G, {task.behavior_dim}) for task "
                         f"{cfg.task_name!r}")
    return _adapt(state, goals, key, cfg, method, jnp.float32(step_size), steps, jnp.float32(t_dist))


def adapt_batch(states: State, goals: jax.Array, keys: jax.Array, cfg: Config, method: str,
                step_size: float = STEP_SIZE, steps: int = STEPS) -> Adapted:
    """`adapt` for S runs' states at once (a sweep's, every array with a leading [S] axis), vmapped.

    goals: [S, G, d], one set per state; keys: [S, 2]. Returns `Adapted` with
    a leading [S] axis. A host-callback physics backend gets all S x G rollouts
    of a step in one call.
    """
    task = get_task(cfg)
    goals = jnp.asarray(goals, jnp.float32)
    _check(states, goals, cfg, method, task, step_size, steps, cfg.t_dist)
    runs = np.shape(states.repertoire.count)
    if goals.ndim != 3 or goals.shape[:1] != runs or np.shape(keys) != (*runs, 2):
        raise ValueError(f"adapt_batch: goals {goals.shape} and keys {np.shape(keys)} must be (S, G, "
                         f"{task.behavior_dim}) and (S, 2) for states of S = {runs} runs")
    size, t_dist = jnp.float32(step_size), jnp.float32(cfg.t_dist)
    return jax.vmap(lambda s, g, k: _adapt(s, g, k, cfg, method, size, steps, t_dist))(states, goals, keys)


def reachable_goals(task: Task, num: int, rng: np.random.Generator) -> np.ndarray:
    """[num, d] goals uniform in the reachable part of the behavior box (rejection sampling; the paper's
    "randomly generated desired behaviors")."""
    low, high = np.asarray(task.behavior_low), np.asarray(task.behavior_high)
    goals = np.empty((0, len(low)), np.float32)
    while len(goals) < num:
        draw = rng.uniform(low, high, (2 * num, len(low))).astype(np.float32)
        goals = np.concatenate([goals, draw[task.reachable(draw)]])
    return goals[:num]
