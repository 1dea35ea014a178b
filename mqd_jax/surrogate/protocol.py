"""What a surrogate is: the small protocol a `ModelEmitter`'s model keeps, and how the emitter reads any of them.

A surrogate is a frozen object (any class, no base to subclass) with three pure, jittable functions over a
state of its own (any pytree):

    state = surrogate.init(key, task, capacity)
    state, loss = surrogate.fit(key, state, repertoire, task, params)
    behaviors, qualities = surrogate.predict(state, actions, task)

Its contract:

* `init` gets the repertoire's `capacity` (C): a surrogate that keeps its training data sizes it from that.
* `fit` learns from the repertoire (`Repertoire`: actions [C, n], behaviors [C, d], qualities [C], `valid` [C],
  `count`; the skills inserted this generation included); the emitter calls it after every generation once
  warm-up is over (the repertoire may still be empty then). It returns a state of `init`'s structure, shapes
  and dtypes, and a float32 loss (any measure of the fit; NaN if none).
* `predict` gives behaviors [N, d] and qualities [N] (real units) of actions [N, n]. It must be differentiable
  in the actions (steering and `adapt(..., "model")` take `jax.jacfwd`/`jax.jacrev` of it). It may be called
  before the first `fit` (during warm-up its predictions are not used).

Optionally:

* `members(state, actions, task) -> [E, N, d + 1]`: an ensemble's E predictions (behavior, quality); the
  rules read their disagreement as `Judged.spread`. Without it, `predict` is the one member.
* `default_params()` and `check_params(params)`: traced parameters (read as `params` in `fit`); without
  them, `params` is ().
* `check_task(task)`: raise ValueError for a task the surrogate cannot serve, before anything is traced.
* `observe(key, state, actions, rollout, evaluated, task, params, features)`: the state after a generation's
  rollouts (actions [P, n], `rollout` [P], `Evaluated`), warm-up included: a surrogate that learns from every
  rollout, not only the repertoire's skills (`mqd_jax.surrogate.local.LocalLinear`). Without it, the state is
  kept.

What is not the surrogate's: warm-up (when `fit` is first called), anchoring (predicting from a known skill's
outcome: the part `Anchoring`), the held-out prediction error and what the rules make of predictions.
The model emitter does those around any surrogate. The built-in `mqd_jax.surrogate.surrogate.Surrogate`
(a network or ensemble, with task features, a gate and a validity classifier) keeps the protocol and a few
more hooks of its own (`Hooks`); `hooks(surrogate)` gives the emitter the same hooks for any surrogate, with
their neutral defaults.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import jax
import jax.numpy as jnp

from mqd_jax.core.checks import shapes_of as _shapes
from mqd_jax.core.emitter import Evaluated
from mqd_jax.core.params import check_params_of, params_of
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.task import Task
from mqd_jax.surrogate.surrogate import Surrogate


class ForwardModel(Protocol):
    """A surrogate (module doc): `init`, `fit` and `predict`; optionally `members`, `default_params`,
    `check_params` and `check_task`."""

    def init(self, key: jax.Array, task: Task, capacity: int) -> Any:
        """The state before any data."""

    def fit(self, key: jax.Array, state: Any, repertoire: Repertoire, task: Task,
            params: Any) -> tuple[Any, jax.Array]:
        """The state after learning from the repertoire, and a float32 loss."""

    def predict(self, state: Any, actions: jax.Array, task: Task) -> tuple[jax.Array, jax.Array]:
        """Behaviors [N, d] and qualities [N] of actions [N, n]; differentiable in the actions."""


def is_surrogate(value: Any) -> bool:
    """Whether `value` has a surrogate's three functions (`ForwardModel`)."""
    return all(callable(getattr(value, name, None)) for name in ("init", "fit", "predict"))


@dataclasses.dataclass(frozen=True)
class Hooks:
    """Any surrogate as the model emitter reads it: the protocol with every optional hook filled in.

    The built-in `Surrogate` has all of these itself; `hooks` wraps any other surrogate in this class, whose
    hooks are neutral: network inputs are the actions, no features are kept, a rollout is observed only by a
    surrogate with its own `observe`, no gate overrules a prediction and no validity classifier judges a candidate.
    """

    model: Any

    validity = None

    def check_task(self, task: Task) -> None:
        check = getattr(self.model, "check_task", None)
        if check is not None:
            check(task)

    def default_params(self) -> Any:
        return params_of(self.model)

    def check_params(self, params: Any) -> None:
        check_params_of(self.model, params)

    def init(self, key: jax.Array, task: Task, capacity: int) -> Any:
        return self.model.init(key, task, capacity)

    def fit(self, key: jax.Array, state: Any, repertoire: Repertoire, task: Task,
            params: Any) -> tuple[Any, jax.Array]:
        """The model's, its state checked against the one it was given (structure, shapes, dtypes) and its loss a
        real scalar: ValueError naming the model otherwise."""
        new, loss = self.model.fit(key, state, repertoire, task, params)
        _check_state(self.model, "fit", new, state)
        if jnp.shape(loss) != () or not jnp.issubdtype(jnp.result_type(loss), jnp.floating):
            raise ValueError(f"{_name(self.model)}.fit returned a loss {_shapes(loss)}; expected a float scalar")
        return new, jnp.asarray(loss, jnp.float32)

    def predict(self, state: Any, actions: jax.Array, task: Task) -> tuple[jax.Array, jax.Array]:
        """As the model's, of actions [N, n] or of one action [n] (what steering and adaptation differentiate);
        ValueError naming the model where it returns other shapes than behaviors [N, d] and qualities [N] or
        other than floats."""
        if actions.ndim == 1:
            behaviors, qualities = self.predict(state, actions[None], task)
            return behaviors[0], qualities[0]
        out = self.model.predict(state, actions, task)
        n, d = actions.shape[0], task.behavior_dim
        if not (isinstance(out, tuple | list) and len(out) == 2 and jnp.shape(out[0]) == (n, d)
                and jnp.shape(out[1]) == (n,) and all(jnp.issubdtype(jnp.result_type(x), jnp.floating) for x in out)):
            raise ValueError(f"{_name(self.model)}.predict returned {_shapes(out)} for {n} actions; expected "
                             f"behaviors float[{n}, {d}] and qualities float[{n}] (the task's {d} behavior dimensions)")
        return out

    def featured(self, task: Task) -> bool:
        return False

    def inputs(self, actions: jax.Array, task: Task) -> jax.Array:
        return actions

    def skill_inputs(self, repertoire: Repertoire, slots: jax.Array, task: Task) -> jax.Array:
        return repertoire.actions[slots]

    def members(self, state: Any, actions: jax.Array, task: Task, inputs: jax.Array | None = None) -> jax.Array:
        """The model's `members` (checked: float [E, N, d + 1]), else its `predict` as the one member."""
        own = getattr(self.model, "members", None)
        if own is None:
            behaviors, qualities = self.predict(state, actions, task)
            return jnp.concatenate([behaviors, qualities[:, None]], axis=-1)[None]
        out, want = own(state, actions, task), (actions.shape[0], task.behavior_dim + 1)
        if jnp.ndim(out) != 3 or jnp.shape(out)[1:] != want or not jnp.issubdtype(jnp.result_type(out), jnp.floating):
            raise ValueError(f"{_name(self.model)}.members returned {_shapes(out)}; expected float[E, {want[0]}, "
                             f"{want[1]}] (each member's behaviors and quality)")
        return out

    def overrule(self, state: Any, inputs: jax.Array, predictions: jax.Array, task: Task) -> jax.Array:
        return predictions

    def usable(self, state: Any, actions: jax.Array, task: Task) -> None:
        return None

    def observe(self, key: jax.Array, state: Any, actions: jax.Array, rollout: jax.Array, evaluated: Evaluated,
                task: Task, params: Any, features: jax.Array | None = None) -> Any:
        """The model's `observe` where it has one (its state checked as `fit`'s), else the state as it is."""
        own = getattr(self.model, "observe", None)
        if own is None:
            return state
        new = own(key, state, actions, rollout, evaluated, task, params, features)
        _check_state(self.model, "observe", new, state)
        return new

    def metrics(self) -> dict[str, Any]:
        return {}

    def report(self, validity: jax.Array | None, rollout: jax.Array, evaluated: Evaluated) -> dict[str, jax.Array]:
        return {}


def _name(part: Any) -> str:
    return type(part).__name__


def _check_state(model: Any, function: str, new: Any, state: Any) -> None:
    """ValueError naming `model.function` where the state it returned is not of the structure, shapes and dtypes
    of the one it was given."""
    if jax.tree.structure(new) != jax.tree.structure(state) or any(
            jnp.shape(a) != jnp.shape(b) or jnp.result_type(a) != jnp.result_type(b)
            for a, b in zip(jax.tree.leaves(new), jax.tree.leaves(state), strict=True)):
        raise ValueError(f"{_name(model)}.{function} returned a state {_shapes(new)}; expected one of the structure, "
                         f"shapes and dtypes it was given, {_shapes(state)} (init's)")


def hooks(surrogate: Any) -> Any:
    """`surrogate` itself where it is the built-in `Surrogate` (it has every hook of `Hooks`), else wrapped in
    `Hooks`."""
    return surrogate if isinstance(surrogate, Surrogate) else Hooks(surrogate)
