"""Anchoring: predicting a candidate from a known skill's true outcome, and the held-out error that decides it.

`ModelEmitter(anchoring=...)`: "always" anchors a candidate's prediction at a repertoire skill a_j near it,
whose true outcome is known: b~(a) = b(a_j) + phi(a) - phi(a_j), and likewise the quality. The model then only
has to predict differences between nearby actions, which helps where behavior is smooth in the action and
hurts across discontinuities (contact). "auto" keeps an exponential average (weight `ERROR_AVERAGING`) of both
predictions' held-out behavior error on every generation's rollouts and uses the one whose average is lower
(the plain one until both have one). `anchor` says which skill: "parent", the one the candidate was varied
from, as the inner emitter names it (a candidate without one, -1, keeps its plain prediction; where the inner
emitter names none, the nearest); "nearest", the skill nearest to it in normalized action space, found by a
search over the repertoire. It works with any surrogate (`mqd_jax.surrogate.protocol`): phi is its `members`.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import repertoire as repertoire_lib
from mqd_jax.core.averages import running_average
from mqd_jax.core.emitter import Evaluated
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.task import Task
from mqd_jax.surrogate import model

ANCHORING = ("none", "always", "auto")
ANCHORS = ("parent", "nearest")
# The weight of a generation's held-out error in anchoring="auto"'s averages.
ERROR_AVERAGING = 0.2


def prediction_error(predicted: jax.Array, evaluated: Evaluated) -> jax.Array:
    """Behavior MSE (real units) of predictions [P, d] on the usable rollouts; NaN if there is none."""
    usable = evaluated.usable
    sq_err = jnp.where(usable[:, None], (predicted - evaluated.behaviors) ** 2, 0.0).sum()
    return jnp.where(usable.any(), sq_err / (usable.sum() * predicted.shape[-1]), jnp.nan)


def predictions(surrogate: Any, state: Any, actions: jax.Array, repertoire: Repertoire, task: Task,
                anchoring: str, anchor: str, parents: jax.Array | None = None,
                x: jax.Array | None = None) -> tuple[jax.Array, jax.Array | None]:
    """The members' plain predictions [E, N, d + 1] of actions [N, n] (their inputs x where computed already) by
    `surrogate` (`protocol.hooks`) and, unless `anchoring` is "none", the anchored ones: at the parents' slots
    [N] (-1: not anchored) with anchor="parent" and parents given, else at the nearest skills. Both as the
    surrogate's `overrule` leaves them."""
    x = surrogate.inputs(actions, task) if x is None else x
    plain = surrogate.members(state, actions, task, x)
    overrule = lambda y: surrogate.overrule(state, x, y, task)  # noqa: E731
    if anchoring == "none":
        return overrule(plain), None
    if anchor == "parent" and parents is not None:
        at, anchored_rows = jnp.maximum(parents, 0), (parents >= 0)[:, None]
    else:
        units = lambda a: model.normalize_actions(a, task)  # noqa: E731
        # Many action dimensions: distances by matrix product (an anchor need only be near, not exactly nearest).
        _, at = repertoire_lib.nearest(repertoire, units(repertoire.actions), units(actions), exact=False)
        anchored_rows = repertoire.count > 0
    known = jnp.concatenate([repertoire.behaviors[at], repertoire.qualities[at, None]], axis=-1)
    anchored = known + plain - surrogate.members(state, repertoire.actions[at], task,
                                                 surrogate.skill_inputs(repertoire, at, task))
    return overrule(plain), overrule(jnp.where(anchored_rows, anchored, plain))


def chosen(anchoring: str, errors: Any, plain: jax.Array, anchored: jax.Array | None) -> jax.Array:
    """The predictions [E, N, d + 1] `anchoring` trusts: the plain ones, the anchored ones, or ("auto") whichever
    had the lower averaged held-out error (`errors` [2]: plain, anchored)."""
    if anchoring == "always":
        return anchored
    if anchoring == "auto":
        return jnp.where(errors[1] < errors[0], anchored, plain)
    return plain


def init(anchoring: str) -> Any:
    """The averaged errors before any: [2] NaN for "auto", else ()."""
    return jnp.full(2, jnp.nan, jnp.float32) if anchoring == "auto" else ()


def averaged(errors: Any, both_behaviors: jax.Array, evaluated: Evaluated) -> jax.Array:
    """"auto"'s errors [2] after a generation whose rollouts were predicted as both_behaviors [2, P, d] (the plain,
    the anchored): each enters its average where it is defined."""
    new = jax.vmap(prediction_error, in_axes=(0, None))(both_behaviors, evaluated)
    return running_average(errors, new, ERROR_AVERAGING, ~jnp.isnan(new))
