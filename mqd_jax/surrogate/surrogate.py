"""The built-in surrogate: a network (or an ensemble) with its training data, task features, gate and validity
classifier, as one part a `ModelEmitter` composes.

`Surrogate` keeps the surrogate protocol (`mqd_jax.surrogate.protocol`: `init`, `fit`, `predict`) and the
hooks the model emitter reads where a surrogate has them. It holds the forward model
(`mqd_jax.surrogate.model`: one network or a vmapped ensemble), its training data (the repertoire, or a ring
buffer of the latest usable rollouts, filled by `observe` after every generation) and an optional classifier
of usable rollouts (`Validity`, trained in `observe`). It predicts (`members`, `predict`) and learns (`fit`);
its one traced parameter is Adam's learning rate (`SurrogateParams`). With `features` the model also takes
the task's features of an action (`Task.features`: what the task can compute without physics). With a `Gate`
(`mqd_jax.surrogate.gate`, trained in `observe`) it also learns the task's auxiliary outputs from every
rollout, and `overrule` moves a candidate the gate says does not act to the null outcome (the object stays
where it is). Warm-up, anchoring and the held-out error are the `ModelEmitter`'s; what to do with the
predictions (the inner emitter, the acquisition rule, fallback and steering) too.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import archive as archive_lib
from mqd_jax.core import pytree
from mqd_jax.core.checks import check_traced, is_int, is_real
from mqd_jax.core.emitter import Evaluated
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.task import Task, feature_dim
from mqd_jax.surrogate import model
from mqd_jax.surrogate.gate import Gate
from mqd_jax.surrogate.validity import Validity, auc

TRAINING_DATA = ("repertoire", "rollouts")


@pytree.dataclass
class SurrogateParams:
    """The surrogate's traced parameter: Adam's `learning_rate` (its validity classifier's too)."""

    learning_rate: jax.Array


@pytree.dataclass
class SurrogateState:
    """What the surrogate carries from one generation to the next.

    Attributes:
      model: the forward model's parameters and optimizer state.
      rollouts: the buffer of the latest usable rollouts the model trains on
        (`archive.Archive` of `rollout_buffer` rows), or () when it trains on the repertoire.
      validity: `validity.ValidityState`, or () without a validity classifier.
      gate: `gate.GateState`, or () without a gate.
    """

    model: model.ModelState
    rollouts: Any = ()
    validity: Any = ()
    gate: Any = ()


@dataclasses.dataclass(frozen=True)
class Surrogate:
    """The forward model, its training data, features, gate and validity classifier (module doc).

    Attributes:
      hidden_size: the model's hidden units (per member).
      ensemble_size: the members of the model's ensemble.
      batch_size, num_batches: training mini-batches per generation (per member).
      learning_rate: Adam's rate, the default of the traced `SurrogateParams.learning_rate`.
      training_data: "repertoire" (its skills, as the paper) or "rollouts" (the latest
        `rollout_buffer` usable rollouts, in a ring buffer).
      rollout_buffer: the size of that buffer.
      validity: a `Validity` classifier of usable rollouts that acquisition rules consult, or None.
      features: the model's inputs include the task's features (`Task.features`); the same as False on a
        task without features.
      feature_rows: with `features`, the training rows per generation whose features are computed (drawn
        from the training data; the mini-batches are drawn from them).
      gate: a `Gate` that moves candidates it says do not act to the null outcome, or None.
      novelty_sampling: with the "repertoire" as training data, the mini-batches draw skills in proportion to
        (novelty + 1e-6) ** novelty_sampling (`model.by_novelty`), as the parents of the candidates are drawn in
        proportion to novelty; 0: uniformly (Table II's reading of "mini-batches from the repertoire").
    """

    hidden_size: int = 32
    ensemble_size: int = 1
    batch_size: int = 16
    num_batches: int = 500
    learning_rate: float = 1e-3
    training_data: str = "repertoire"
    rollout_buffer: int = 4096
    validity: Validity | None = None
    features: bool = False
    feature_rows: int = 1024
    gate: Gate | None = None
    novelty_sampling: float = 0.0

    def __post_init__(self) -> None:
        for name, lowest in (("hidden_size", 1), ("ensemble_size", 1), ("batch_size", 1), ("num_batches", 1),
                             ("rollout_buffer", 1), ("feature_rows", 1)):
            value = getattr(self, name)
            if not (is_int(value) and value >= lowest):
                raise ValueError(f"Surrogate.{name}={value!r} is invalid: expected an int >= {lowest}")
        if not (is_real(self.learning_rate) and self.learning_rate > 0):
            raise ValueError(f"Surrogate.learning_rate={self.learning_rate!r} is invalid: expected a finite float > 0")
        if self.training_data not in TRAINING_DATA:
            raise ValueError(f"Surrogate.training_data={self.training_data!r} is invalid: expected one of "
                             f"{TRAINING_DATA}")
        if not isinstance(self.features, bool):
            raise ValueError(f"Surrogate.features={self.features!r} is invalid: expected True or False")
        if self.validity is not None and not isinstance(self.validity, Validity):
            raise ValueError(f"Surrogate.validity={self.validity!r} is invalid: expected None or a Validity")
        if self.gate is not None and not isinstance(self.gate, Gate):
            raise ValueError(f"Surrogate.gate={self.gate!r} is invalid: expected None or a Gate")
        if not (is_real(self.novelty_sampling) and self.novelty_sampling >= 0):
            raise ValueError(f"Surrogate.novelty_sampling={self.novelty_sampling!r} is invalid: expected a finite "
                             "float >= 0 (0: uniform mini-batches)")
        if self.novelty_sampling and self.training_data != "repertoire":
            raise ValueError(f"Surrogate.novelty_sampling={self.novelty_sampling!r} draws skills by their novelty, "
                             f"which training_data={self.training_data!r} does not have: set novelty_sampling=0 or "
                             "training_data='repertoire'")

    def check_task(self, task: Task) -> None:
        """Raises ValueError unless the task gives what the surrogate needs (a gate's auxiliary output)."""
        if self.gate is not None:
            self.gate.check_task(task)

    def featured(self, task: Task) -> bool:
        """Whether the model takes features of `task` (`features` is set and the task has some)."""
        return self.features and feature_dim(task) > 0

    def _gated(self, task: Task) -> bool:
        """Whether a gate acts on `task` (`Gate.serves`)."""
        return self.gate is not None and self.gate.serves(task)

    def _input_size(self, task: Task) -> int:
        return task.action_dim + (feature_dim(task) if self.featured(task) else 0)

    def inputs(self, actions: jax.Array, task: Task, features: jax.Array | None = None) -> jax.Array:
        """The networks' inputs [N, n (+ f)] of actions [N, n] (`model.inputs`), from their features [N, f] where
        known (`Proposal.features`)."""
        if features is not None and self.featured(task):
            return model.inputs_with(actions, features, task)
        return model.inputs(actions, task, self.featured(task))

    def _kept(self, repertoire: Repertoire, task: Task) -> jax.Array | None:
        """The features [C, f] the repertoire keeps per skill (`Repertoire.features`, as `ModelEmitter.keeps_features`
        asks) where they are this model's inputs, else None."""
        kept = self.featured(task) and repertoire.features.shape[-1] == feature_dim(task)
        return repertoire.features if kept else None

    def skill_inputs(self, repertoire: Repertoire, slots: jax.Array, task: Task) -> jax.Array:
        """The networks' inputs of the skills at slots [N], from the features the repertoire keeps where it does."""
        kept = self._kept(repertoire, task)
        return self.inputs(repertoire.actions[slots], task, None if kept is None else kept[slots])

    def default_params(self) -> SurrogateParams:
        return SurrogateParams(jnp.float32(self.learning_rate))

    def check_params(self, params: SurrogateParams) -> None:
        check_traced("Surrogate.params", "learning_rate", params.learning_rate, inclusive=False)

    def init(self, key: jax.Array, task: Task, capacity: int) -> SurrogateState:
        """The untrained model (its buffer and classifiers empty); `capacity`, the repertoire's, is not needed."""
        rollouts = (archive_lib.Archive.empty(self.rollout_buffer, task.action_dim, task.behavior_dim)
                    if self.training_data == "rollouts" else ())
        return SurrogateState(model=model.init(key, self.hidden_size, task, self.ensemble_size,
                                               features=self.features), rollouts=rollouts,
                              validity=() if self.validity is None else self.validity.init(
                                  jax.random.fold_in(key, 3), task),
                              gate=() if not self._gated(task) else self.gate.init(
                                  jax.random.fold_in(key, 4), task, self._input_size(task)))

    def members(self, state: SurrogateState, actions: jax.Array, task: Task,
                inputs: jax.Array | None = None) -> jax.Array:
        """Each member's prediction [E, N, d + 1] (behavior, quality; real units) of actions [N, n] (`inputs`: their
        network inputs where already computed). A subclass may predict otherwise (an experiment's oracle returns
        the true outcomes)."""
        return model.predict_members(state.model, actions, task, self.features, inputs)

    def predict(self, state: SurrogateState, actions: jax.Array, task: Task) -> tuple[jax.Array, jax.Array]:
        """The model's behaviors [..., d] and qualities [...] of actions [..., n] (what steering and skill
        adaptation differentiate; the ensemble's mean, not gated)."""
        return model.predict(state.model, actions, task, self.features)

    def overrule(self, state: SurrogateState, x: jax.Array, predictions: jax.Array, task: Task) -> jax.Array:
        """predictions [E, N, d + 1] of candidates with network inputs x [N, ...], with those the gate says do not
        act moved to the null outcome (unchanged without a gate)."""
        return self.gate.gated(state.gate, x, predictions, task) if self._gated(task) else predictions

    def usable(self, state: SurrogateState, actions: jax.Array, task: Task) -> jax.Array | None:
        """[N] the validity classifier's probability of a usable rollout of actions [N, n], or None without one."""
        return None if self.validity is None else self.validity.probability(state.validity, actions, task)

    def metrics(self) -> dict[str, Any]:
        """The metrics `report` gives: with a validity classifier `validity_auc`."""
        return {} if self.validity is None else {"validity_auc": jnp.float32}

    def report(self, validity: jax.Array | None, rollout: jax.Array, evaluated: Evaluated) -> dict[str, jax.Array]:
        """With a validity classifier, `validity_auc`: among a generation's rollouts (rollout [P]) the probability
        that a usable one had a higher judged probability (validity [P]) of being usable than an unusable one; ties
        1/2; NaN without both."""
        if self.validity is None:
            return {}
        return {"validity_auc": auc(validity, rollout & evaluated.usable, rollout & ~evaluated.usable)}

    def fit(self, key: jax.Array, state: SurrogateState, repertoire: Repertoire, task: Task,
            params: SurrogateParams) -> tuple[SurrogateState, jax.Array]:
        """The model trained on the repertoire (the features it keeps) or its rollout buffer, and the mean
        training loss (NaN where the buffer is empty)."""
        data = repertoire if self.training_data == "repertoire" else state.rollouts
        has_data = repertoire.count > 0 if self.training_data == "repertoire" else state.rollouts.total > 0
        trained, loss = jax.lax.cond(
            has_data, lambda: model.train(state.model, key, data, task, params.learning_rate, self.batch_size,
                                          self.num_batches, self.feature_rows if self.featured(task) else None,
                                          self._kept(repertoire, task)
                                          if self.training_data == "repertoire" else None, self.novelty_sampling),
            lambda: (state.model, jnp.float32(jnp.nan)))
        return state.replace(model=trained), loss

    def observe(self, key: jax.Array, state: SurrogateState, actions: jax.Array, rollout: jax.Array,
                evaluated: Evaluated, task: Task, params: SurrogateParams,
                features: jax.Array | None = None) -> SurrogateState:
        """The state after a generation's rollouts of actions [P] (`rollout` [P]: rolled out; `features` [P, f]
        their features where known), warm-up included: the rollout buffer takes the usable ones, the validity
        classifier and the gate train on them."""
        rollouts = state.rollouts
        if self.training_data == "rollouts":
            rollouts = archive_lib.push(state.rollouts, actions, evaluated.behaviors, evaluated.qualities,
                                        evaluated.usable)
        validity = state.validity
        if self.validity is not None:
            validity = self.validity.update(jax.random.fold_in(key, 3), state.validity, actions, rollout,
                                            evaluated.usable, task, params.learning_rate)
        gate = state.gate
        if self._gated(task):
            outcomes = jnp.concatenate([evaluated.behaviors, evaluated.qualities[:, None]], axis=1)
            gate = self.gate.update(jax.random.fold_in(key, 4), state.gate, self.inputs(actions, task, features),
                                    evaluated.auxiliary, outcomes, evaluated.usable, task, params.learning_rate)
        return state.replace(rollouts=rollouts, validity=validity, gate=gate)
