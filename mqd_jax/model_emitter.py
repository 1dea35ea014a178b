"""M-QD's model as an emitter wrapper: a learned forward model decides which of another emitter's candidates
are worth a rollout (paper, "Model-Based Quality-Diversity Search", Algorithm 1).

`ModelEmitter(inner, acquisition)` asks `inner` for a pool of candidates,
predicts their behaviors and qualities with its model (`mqd_jax.model`), scores
them against the repertoire and lets the acquisition rule choose
(`mqd_jax.acquisition`: the paper's `Threshold` filter or `Budgeted` ranking).
Until `warmup_samples` of its candidates were rolled out the rule passes the
inner emitter's proposal through. After every generation past warm-up it trains
the model on the repertoire. It owns the model's state and reports the model's
metrics; any emitter can be the inner one.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
from flax import struct

from mqd_jax import acquisition, model
from mqd_jax.emitters import Emitter, Evaluated, Proposal
from mqd_jax.repertoire import Repertoire
from mqd_jax.task import Task

if TYPE_CHECKING:
    from mqd_jax.config import Params

_METRICS = {"discarded": jnp.int32, "model_loss": jnp.float32, "prediction_error": jnp.float32}


@struct.dataclass
class ModelEmitterState:
    """The wrapper's state.

    Attributes:
      model: the forward model's parameters and optimizer state.
      inner: the inner emitter's state.
      evaluations: int32, this emitter's candidates rolled out so far (warm-up counts them).
    """

    model: model.ModelState
    inner: Any
    evaluations: jax.Array


@dataclasses.dataclass(frozen=True)
class ModelEmitter(Emitter):
    """Filters or ranks `inner`'s candidates with a learned forward model.

    Attributes:
      inner: the emitter whose candidates the model judges.
      acquisition: the rule that picks the candidates to roll out.
      k: the repertoire neighbours the predicted novelty and improvement average over.
      hidden_size: the model's hidden units.
      batch_size, num_batches: training mini-batches per generation.
      warmup_samples: rollouts before the model is trained and used.

    Metrics: `discarded` (candidates the model turned down), `model_loss`
    (mean training loss of the generation's mini-batches; NaN when it did not
    train), `prediction_error` (behavior MSE in real units of the predictions
    on this generation's usable rollouts, before training on them; NaN if
    none), and the inner emitter's.
    """

    inner: Emitter
    acquisition: acquisition.Acquisition = dataclasses.field(default_factory=acquisition.Threshold)
    k: int = 5
    hidden_size: int = 32
    batch_size: int = 16
    num_batches: int = 500
    warmup_samples: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.inner, Emitter):
            raise ValueError(f"ModelEmitter.inner={self.inner!r} is invalid: expected an Emitter")
        for name, lowest in (("k", 1), ("hidden_size", 1), ("batch_size", 1), ("num_batches", 1),
                             ("warmup_samples", 0)):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= lowest):
                raise ValueError(f"ModelEmitter.{name}={value!r} is invalid: expected an int >= {lowest}")
        clash = set(_METRICS) & set(self.inner.metrics())
        if clash:
            raise ValueError(f"ModelEmitter: the inner emitter's metrics {sorted(clash)} clash with the model's")

    def init(self, key: jax.Array, task: Task) -> ModelEmitterState:
        return ModelEmitterState(model=model.init(key, self.hidden_size, task),
                                 inner=self.inner.init(jax.random.fold_in(key, 1), task), evaluations=jnp.int32(0))

    def propose(self, key: jax.Array, state: ModelEmitterState, repertoire: Repertoire, task: Task, params: Params,
                num: int) -> Proposal:
        pool_size = self.acquisition.pool_size(num)
        pool = self.inner.propose(key, state.inner, repertoire, task, params, pool_size)
        pred_behaviors, pred_qualities = model.predict(state.model, pool.actions, task)
        novelty, improvement = acquisition.predicted_scores(pred_behaviors, pred_qualities, repertoire, self.k)
        warm_up = state.evaluations < self.warmup_samples
        rows, rollout, discarded = self.acquisition.select(novelty, improvement, pool.rollout, warm_up, params, num)
        keep = lambda x: x[rows] if jnp.ndim(x) and jnp.shape(x)[0] == pool_size else x  # noqa: E731
        info = {"inner": jax.tree.map(keep, pool.info), "predicted_behaviors": pred_behaviors[rows],
                "discarded": discarded}
        return Proposal(pool.actions[rows], rollout, info)

    def update(self, key: jax.Array, state: ModelEmitterState, proposal: Proposal, evaluated: Evaluated,
               repertoire: Repertoire, task: Task, params: Params) -> tuple[ModelEmitterState, dict[str, jax.Array]]:
        evaluations = state.evaluations + proposal.rollout.sum(dtype=jnp.int32)
        due = (evaluations >= self.warmup_samples) & (repertoire.count > 0)
        trained, loss = jax.lax.cond(
            due, lambda: model.train(state.model, key, repertoire, task, params.learning_rate, self.batch_size,
                                     self.num_batches),
            lambda: (state.model, jnp.float32(jnp.nan)))
        inner_proposal = Proposal(proposal.actions, proposal.rollout, proposal.info["inner"])
        inner, inner_metrics = self.inner.update(jax.random.fold_in(key, 1), state.inner, inner_proposal, evaluated,
                                                 repertoire, task, params)
        metrics = {"discarded": proposal.info["discarded"], "model_loss": loss,
                   "prediction_error": _prediction_error(proposal.info["predicted_behaviors"], evaluated),
                   **inner_metrics}
        return ModelEmitterState(model=trained, inner=inner, evaluations=evaluations), metrics

    def metrics(self) -> dict[str, Any]:
        return {**_METRICS, **self.inner.metrics()}

    def predict(self, state: ModelEmitterState, actions: jax.Array, task: Task) -> tuple[jax.Array, jax.Array]:
        """The model's behaviors [..., d] and qualities [...] of actions [..., n] (what skill adaptation uses)."""
        return model.predict(state.model, actions, task)


def _prediction_error(predicted: jax.Array, evaluated: Evaluated) -> jax.Array:
    """Behavior MSE (real units) of predictions [P, d] on the usable rollouts; NaN if there is none."""
    usable = evaluated.usable
    sq_err = jnp.where(usable[:, None], (predicted - evaluated.behaviors) ** 2, 0.0).sum()
    return jnp.where(usable.any(), sq_err / (usable.sum() * predicted.shape[-1]), jnp.nan)
