"""Which actions give a usable rollout: a classifier a model-based emitter consults (`ModelEmitter(validity=...)`).

A rollout can be unusable: the task calls it invalid (a via-point out of the
arm's reach, the arm touching the table, a cube lost on the way) or its
outcome is not finite. The forward model trains on the repertoire's skills,
all of them usable, so it knows nothing of this, and a rule that chases
predicted novelty favours the candidates it extrapolates on, many of them
unusable (measured on Place: 42% of `"mqd"`'s rollouts; docs/results.md).

`Validity` keeps a ring buffer of the emitter's rolled-out actions with
whether each was usable, fits a network of the forward model's kind (one
hidden layer, tanh output; `mqd_jax.surrogate.model.fit`) to +1 (usable) and -1
(unusable) by mean-squared error, and judges a candidate's probability of a
usable rollout as (output + 1) / 2, in [0, 1] (the squared error of a
probability is the Brier score, a proper scoring rule, so the fit estimates
that probability). Until the buffer has held an unusable rollout it neither
trains nor judges: every candidate's probability is exactly 1, so on a task
whose rollouts are all usable a run is the same as without it.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from mqd_jax.core import archive as archive_lib
from mqd_jax.core import pytree
from mqd_jax.core.checks import is_int
from mqd_jax.core.task import Task
from mqd_jax.surrogate import model


@pytree.dataclass
class ValidityState:
    """The classifier's state.

    Attributes:
      model: its network (`model.ModelState`, one member, one output).
      buffer: the latest rolled-out actions (`archive.Archive` of `buffer_size` rows: actions [B, n]; its
        `qualities` column [B] holds the label, 1.0 usable and 0.0 not; behaviors [B, 0]).
      unusable: int32, unusable rollouts seen so far.
    """

    model: model.ModelState
    buffer: archive_lib.Archive
    unusable: jax.Array


@dataclasses.dataclass(frozen=True)
class Validity:
    """A classifier of usable rollouts, trained after every generation on a buffer of the latest rollouts.

    Attributes:
      hidden_size: its hidden units.
      buffer_size: the rollouts it remembers (a ring buffer).
      batch_size, num_batches: its Adam steps per generation (at the config's learning rate).
    """

    hidden_size: int = 32
    buffer_size: int = 4096
    batch_size: int = 64
    num_batches: int = 100

    def __post_init__(self) -> None:
        for name in ("hidden_size", "buffer_size", "batch_size", "num_batches"):
            value = getattr(self, name)
            if not (is_int(value) and value >= 1):
                raise ValueError(f"Validity.{name}={value!r} is invalid: expected an int >= 1")

    def init(self, key: jax.Array, task: Task) -> ValidityState:
        return ValidityState(model=model.init(key, self.hidden_size, task, out_size=1),
                             buffer=archive_lib.Archive.empty(self.buffer_size, task.action_dim, 0),
                             unusable=jnp.int32(0))

    def probability(self, state: ValidityState, actions: jax.Array, task: Task) -> jax.Array:
        """[N] the probability that each of actions [N, n] gives a usable rollout (1 before any unusable one)."""
        output = model.apply_members(state.model, model.normalize_actions(actions, task))[0, :, 0]
        return jnp.where(state.unusable > 0, (output + 1.0) / 2.0, 1.0)

    def update(self, key: jax.Array, state: ValidityState, actions: jax.Array, rolled_out: jax.Array,
               usable: jax.Array, task: Task, learning_rate: jax.Array) -> ValidityState:
        """Remembers the rolled-out rows of actions [P, n] (rolled_out [P]) with usable [P], then trains (once an
        unusable rollout was seen)."""
        buffer = archive_lib.push(state.buffer, actions, jnp.zeros((actions.shape[0], 0), jnp.float32),
                                  usable.astype(jnp.float32), rolled_out)
        unusable = state.unusable + (rolled_out & ~usable).sum(dtype=jnp.int32)
        filled = jnp.minimum(buffer.total, self.buffer_size)
        trained = jax.lax.cond(
            unusable > 0,
            lambda: model.fit(state.model, key, model.normalize_actions(buffer.actions, task),
                              2.0 * buffer.qualities[:, None] - 1.0, filled, learning_rate, self.batch_size,
                              self.num_batches)[0],
            lambda: state.model)
        return ValidityState(model=trained, buffer=buffer, unusable=unusable)


def auc(score: jax.Array, positive: jax.Array, negative: jax.Array) -> jax.Array:
    """P(score of a positive row > score of a negative one) over score [P] and the masks [P], ties 1/2; NaN
    without both kinds. NaN scores count as the lowest."""
    score = jnp.nan_to_num(score, nan=-jnp.inf)
    pairs = positive[:, None] & negative[None, :]
    wins = jnp.where(score[:, None] > score[None, :], 1.0, jnp.where(score[:, None] == score[None, :], 0.5, 0.0))
    n = pairs.sum()
    return jnp.where(n > 0, jnp.where(pairs, wins, 0.0).sum() / jnp.maximum(n, 1), jnp.nan)
