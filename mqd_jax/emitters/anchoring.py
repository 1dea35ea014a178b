"""Anchoring: predicting a candidate from a known skill's true outcome, and the held-out error that decides it.

`Anchoring(mode)` in a `ModelEmitter`'s chain of parts: "always" anchors a candidate's prediction at a
repertoire skill a_j near it, whose true outcome is known: b~(a) = b(a_j) + phi(a) - phi(a_j), and likewise the
quality. The model then only has to predict differences between nearby actions, which helps where behavior is
smooth in the action and hurts across discontinuities (contact). "auto" keeps an exponential average (weight
`ERROR_AVERAGING`) of both predictions' held-out behavior error on every generation's rollouts and uses the one
whose average is lower (the plain one until both have one). `anchor` says which skill: "parent", the one the
candidate was varied from, as the inner emitter names it (a candidate without one, -1, keeps its plain
prediction; where the inner emitter names none, the nearest); "nearest", the skill nearest to it in normalized
action space, found by a search over the repertoire. It works with any surrogate (`mqd_jax.surrogate.protocol`):
phi is its `members`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import repertoire as repertoire_lib
from mqd_jax.core.averages import running_average
from mqd_jax.core.emitter import Evaluated
from mqd_jax.core.task import Task
from mqd_jax.emitters.parts import Part, Pooled, View
from mqd_jax.surrogate import model as model_lib

MODES = ("always", "auto")
ANCHORS = ("parent", "nearest")
# The weight of a generation's held-out error in Anchoring("auto")'s averages.
ERROR_AVERAGING = 0.2


def prediction_error(predicted: jax.Array, evaluated: Evaluated) -> jax.Array:
    """Behavior MSE (real units) of predictions [P, d] on the usable rollouts; NaN if there is none."""
    usable = evaluated.usable
    sq_err = jnp.where(usable[:, None], (predicted - evaluated.behaviors) ** 2, 0.0).sum()
    return jnp.where(usable.any(), sq_err / (usable.sum() * predicted.shape[-1]), jnp.nan)


@dataclasses.dataclass(frozen=True)
class Anchoring(Part):
    """Anchored predictions (a part of a `ModelEmitter`'s chain; module doc).

    Attributes:
      mode: "always" (every prediction anchored) or "auto" (whichever of the plain and the anchored predictions
        has had the lower averaged held-out error).
      anchor: "parent" (the skill the candidate was varied from) or "nearest" (the nearest skill in normalized
        action space).
    """

    mode: str = "auto"
    anchor: str = "parent"

    name = "anchoring"
    learns_in_warm_up = True  # its errors are measured from the first generation on

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"Anchoring.mode={self.mode!r} is invalid: expected one of {MODES}")
        if self.anchor not in ANCHORS:
            raise ValueError(f"Anchoring.anchor={self.anchor!r} is invalid: expected one of {ANCHORS}")

    def init(self, key: jax.Array, task: Task) -> Any:
        """The averaged errors before any: [2] NaN (plain, anchored) for "auto", else ()."""
        return jnp.full(2, jnp.nan, jnp.float32) if self.mode == "auto" else ()

    def predicted(self, state: Any, y: jax.Array, candidates: Pooled, view: View) -> tuple[jax.Array, Any]:
        """The predictions [E, N, d + 1] this part trusts, from the plain ones y (as the surrogate's `overrule`
        leaves them), and ("auto") both predictions' behaviors [N, 2, d] for the held-out errors."""
        anchored = self.anchored(candidates, view)
        if self.mode == "always":
            return anchored, ()
        both = jnp.stack([y.mean(axis=0)[:, :-1], anchored.mean(axis=0)[:, :-1]], axis=1)
        return jnp.where(state[1] < state[0], anchored, y), both

    def anchored(self, candidates: Pooled, view: View) -> jax.Array:
        """The members' anchored predictions [E, N, d + 1] of the candidates, as the surrogate's `overrule`
        leaves them: at the parents' slots (-1: not anchored) with anchor="parent" where the pool names parents,
        else at the nearest skills."""
        model, state, repertoire, task = view.model, view.surrogate, view.repertoire, view.task
        parents, plain = candidates.parents, candidates.members
        if self.anchor == "parent" and parents is not None:
            at, anchored_rows = jnp.maximum(parents, 0), (parents >= 0)[:, None]
        else:
            units = lambda a: model_lib.normalize_actions(a, task)  # noqa: E731
            # Many action dimensions: distances by matrix product (an anchor need only be near, not exactly nearest).
            _, at = repertoire_lib.nearest(repertoire, units(repertoire.actions), units(candidates.actions),
                                           exact=False)
            anchored_rows = repertoire.count > 0
        known = jnp.concatenate([repertoire.behaviors[at], repertoire.qualities[at, None]], axis=-1)
        anchored = known + plain - model.members(state, repertoire.actions[at], task,
                                                 model.skill_inputs(repertoire, at, task))
        return model.overrule(state, candidates.x, jnp.where(anchored_rows, anchored, plain), task)

    def update(self, state: Any, info: Any, proposal: Any, evaluated: Evaluated) -> Any:
        """"auto"'s errors [2] after a generation whose rollouts were predicted as info[1] [P, 2, d] (the plain,
        the anchored behaviors): each enters its average where it is defined."""
        if self.mode == "always":
            return state
        new = jax.vmap(prediction_error, in_axes=(0, None))(jnp.moveaxis(info[1], 1, 0), evaluated)
        return running_average(state, new, ERROR_AVERAGING, ~jnp.isnan(new))
