"""M-QD's model as an emitter wrapper: a learned forward model decides which of another emitter's candidates
are worth a rollout (paper, "Model-Based Quality-Diversity Search", Algorithm 1).

`ModelEmitter(inner, acquisition, surrogate, parts=...)` asks `inner` for a pool of candidates, predicts their
behaviors and qualities with its surrogate (any part that keeps the protocol of `mqd_jax.surrogate.protocol`;
the built-in `mqd_jax.surrogate.surrogate.Surrogate`: one network or a vmapped ensemble, its training data,
features, gate and validity classifier), scores them against the repertoire and lets the acquisition rule
choose (`mqd_jax.emitters.acquisition`: the paper's `Threshold` filter, `Budgeted` ranking or `Diverse` batch
selection; or a source that proposes by itself, `imagination.Imagination`). Until `warmup_samples` of its
candidates were rolled out it rolls out the inner emitter's proposal as it came (the rule's choice is not
used). After every generation past warm-up it fits the surrogate (`fit`); the built-in one also `observe`s every
generation's rollouts. It owns the surrogate's state, measures its held-out error and reports the model's
metrics; any emitter can be the inner one.

Everything else is a part in its chain (`mqd_jax.emitters.parts`), run in order at each stage:
`steering.Steering` (children the model's Jacobian aims at empty behavior space, in place of the pool's last
rows), `anchoring.Anchoring` (predictions anchored at a known skill), and the shares `pursuit.Fallback` (adaptive
pursuit between the model's choice and the inner emitter's own candidates) and `step_aside.StepAside` (the
inner emitter's generation while the model explains no more than chance). The presets
(`mqd_jax.emitters.presets`) build the chains.

Metrics: `discarded` (candidates the model turned down), `model_loss` (mean training loss of the generation's
mini-batches; NaN when it did not train), `prediction_error` (behavior MSE in real units of the predictions on
this generation's usable rollouts, before training on them; NaN if none), `opener_auc` (among this generation's
usable rollouts, the probability that one which opened a niche had a larger predicted distance to the nearest
skill than one which did not; ties count 1/2; NaN without both kinds), with a share in the chain `model_share`
(the share of the generation's rows from the rule: 1 during warm-up), the parts' (`Steering`: `steered`,
`steering_share`; `StepAside`: `model_skill`), the surrogate's (with validity: `validity_auc`) and the inner
emitter's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import pytree
from mqd_jax.core import repertoire as repertoire_lib
from mqd_jax.core.checks import is_int
from mqd_jax.core.emitter import Emitter, Evaluated, Proposal, init_emitter
from mqd_jax.core.params import Params, check_params_of, params_of
from mqd_jax.core.repertoire import AddStatus, Repertoire
from mqd_jax.core.task import Task
from mqd_jax.emitters import acquisition, contracts, parts
from mqd_jax.emitters.anchoring import prediction_error
from mqd_jax.emitters.parts import ModelInfo, Pooled, View
from mqd_jax.surrogate import protocol
from mqd_jax.surrogate.surrogate import Surrogate
from mqd_jax.surrogate.validity import auc

_METRICS = {"discarded": jnp.int32, "model_loss": jnp.float32, "prediction_error": jnp.float32,
            "opener_auc": jnp.float32}


@pytree.dataclass
class ModelEmitterParams:
    """A `ModelEmitter`'s traced parameters: its parts' own (the surrogate's (the built-in's learning rate), the
    inner emitter's and the acquisition rule's)."""

    surrogate: Any
    inner: Any = ()
    acquisition: Any = ()


@pytree.dataclass
class ModelEmitterState:
    """The wrapper's state.

    Attributes:
      surrogate: the surrogate's state (the built-in's `SurrogateState`: the model, its training data, gate,
        validity).
      inner: the inner emitter's state.
      evaluations: int32, this emitter's candidates rolled out so far (warm-up counts them).
      acquisition: the rule's state (its `init`), or ().
      parts: {part.name: its state} of the chain's parts.
    """

    surrogate: Any
    inner: Any
    evaluations: jax.Array
    acquisition: Any = ()
    parts: dict[str, Any] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class ModelEmitter(Emitter):
    """Filters or ranks `inner`'s candidates with a learned forward model (module doc).

    Attributes:
      inner: the emitter whose candidates the model judges.
      acquisition: the rule that picks the candidates to roll out (`acquisition.Acquisition`), or a source that
        proposes by itself (`imagination.Imagination`: an object with `propose(key, emitter, state, repertoire,
        task, params, num)`).
      surrogate: the model (`mqd_jax.surrogate.protocol`: any object with `init`, `fit` and `predict`; the
        built-in `Surrogate` with its training, features, gate and validity classifier).
      k: the repertoire neighbours the predicted novelty and improvement average over.
      warmup_samples: rollouts before the model is trained and used.
      parts: the chain of parts (`mqd_jax.emitters.parts`), run in order: `Steering`, `Anchoring`, `Fallback`,
        `StepAside` or one's own. A part that keeps or replaces the rule's first rows needs a ranking rule.
      checks: check the parts' values every generation as the program runs (`contracts.values`: the rule's rows
        in range and distinct, the surrogate's predictions finite after warm-up), stopping the run with an error
        that names the part; their shapes and dtypes are checked as it is traced, always.

    Metrics: the module doc's.
    """

    inner: Emitter
    acquisition: Any = dataclasses.field(default_factory=acquisition.Threshold)
    surrogate: Any = dataclasses.field(default_factory=Surrogate)
    k: int = 5
    warmup_samples: int = 0
    parts: tuple[Any, ...] = ()
    checks: bool = False

    # Its surrogate may keep data sized by the repertoire (`init(key, task, capacity)`).
    sized = True

    def __post_init__(self) -> None:
        if not isinstance(self.inner, Emitter):
            raise ValueError(f"ModelEmitter.inner={self.inner!r} is invalid: expected an Emitter")
        if not protocol.is_surrogate(self.surrogate):
            raise ValueError(f"ModelEmitter.surrogate={self.surrogate!r} is invalid: expected a surrogate, an object "
                             "with init(key, task, capacity), fit(key, state, repertoire, task, params) and "
                             "predict(state, actions, task) (mqd_jax.surrogate.protocol), such as Surrogate()")
        if not isinstance(self.checks, bool):
            raise ValueError(f"ModelEmitter.checks={self.checks!r} is invalid: expected a bool")
        for name, lowest in (("k", 1), ("warmup_samples", 0)):
            value = getattr(self, name)
            if not (is_int(value) and value >= lowest):
                raise ValueError(f"ModelEmitter.{name}={value!r} is invalid: expected an int >= {lowest}")
        parts.check_chain(self.parts, acquisition.is_ranked(self.acquisition), "ModelEmitter",
                          [_METRICS, self.model.metrics(), self.inner.metrics()])
        getattr(self.acquisition, "check", lambda emitter: None)(self)

    @property
    def model(self) -> Any:
        """The surrogate as this emitter reads it, with every hook (`protocol.hooks`)."""
        return protocol.hooks(self.surrogate)

    def part(self, name: str) -> Any:
        """The chain's part named `name`, or None."""
        return next((part for part in self.parts if part.name == name), None)

    def forward_model(self, state: ModelEmitterState, task: Task) -> tuple[Any, jax.Array]:
        """(action [n] -> predicted behavior [d], trained: warm-up is over and the surrogate was fitted)."""
        return (lambda a: self.model.predict(state.surrogate, a, task)[0]), state.evaluations >= self.warmup_samples

    def default_params(self) -> ModelEmitterParams:
        return ModelEmitterParams(self.model.default_params(), self.inner.default_params(),
                                  params_of(self.acquisition))

    def check_params(self, params: ModelEmitterParams) -> None:
        self.model.check_params(params.surrogate)
        self.inner.check_params(params.inner)
        check_params_of(self.acquisition, params.acquisition)

    def check_run(self, population_size: int, max_generations: int) -> None:
        pool_size = self.acquisition.pool_size(population_size)
        self.inner.check_run(pool_size, max_generations)
        budget = population_size * max_generations
        if self.warmup_samples >= budget:
            raise ValueError(f"ModelEmitter.warmup_samples={self.warmup_samples} is invalid for this run: expected "
                             f"fewer than its population_size x max_generations ({budget}) rollouts, or the model "
                             "is never used")
        for part in self.parts:
            part.check_run(pool_size, population_size)

    def pool_size(self, num: int) -> int:
        return self.inner.pool_size(self.acquisition.pool_size(num))

    def keeps_features(self, task: Task) -> bool:
        """The model takes the task's features: the repertoire keeps each skill's (anchors, training rows)."""
        return self.model.featured(task)

    def check_task(self, task: Task) -> None:
        self.inner.check_task(task)
        self.model.check_task(task)

    def init(self, key: jax.Array, task: Task, capacity: int) -> ModelEmitterState:
        """The state before any rollout; `capacity`: the repertoire's (the run passes its `Config.capacity`)."""
        return ModelEmitterState(surrogate=self.model.init(key, task, capacity),
                                 inner=init_emitter(self.inner, jax.random.fold_in(key, 1), task, capacity),
                                 evaluations=jnp.int32(0),
                                 acquisition=acquisition.state_of(self.acquisition, jax.random.fold_in(key, 5), task),
                                 parts={part.name: init_emitter(part, jax.random.fold_in(key, 6), task, capacity)
                                        for part in self.parts})

    def view(self, state: ModelEmitterState, repertoire: Repertoire, task: Task, params: Params | None,
             num: int) -> View:
        """What the parts see of a generation of `num` rollouts proposed from `state`."""
        return View(self.model, state.surrogate, repertoire, task, params, num,
                    state.evaluations < self.warmup_samples)

    def predicted(self, state: ModelEmitterState, actions: jax.Array, parents: jax.Array | None, x: jax.Array,
                  view: View) -> tuple[jax.Array, dict[str, Any]]:
        """The members' predictions [E, N, d + 1] of actions [N, n] (their parents' slots [N] or None; their
        surrogate inputs x) as the chain's predict stages leave them, and each part's info of that stage."""
        members = self.model.members(state.surrogate, actions, view.task, x)
        y = self.model.overrule(state.surrogate, x, members, view.task)
        candidates, infos = Pooled(actions, parents, x, members), {}
        for part in self.parts:
            y, infos[part.name] = part.predicted(state.parts[part.name], y, candidates, view)
        return y, infos

    def judge(self, state: ModelEmitterState, actions: jax.Array, repertoire: Repertoire, task: Task,
              parents: jax.Array | None = None) -> acquisition.Judged:
        """The model's view of actions [N, n] (their parents' slots [N], or None) against the repertoire."""
        view = self.view(state, repertoire, task, None, actions.shape[0])
        y, _ = self.predicted(state, actions, parents, self.model.inputs(actions, task), view)
        return self._judgement(state, y, actions, parents, view)

    def _judgement(self, state: ModelEmitterState, y: jax.Array, actions: jax.Array, parents: jax.Array | None,
                   view: View) -> acquisition.Judged:
        """The rule's view of candidates [N, n] from their predictions y [E, N, d + 1] against the view's repertoire,
        as the chain's judge stages leave it."""
        judgement = judged(self.model, state.surrogate, y, view.repertoire, actions, view.task, parents, view.warm_up,
                           self.k)
        return parts.judged(self.parts, state.parts, judgement, view)

    def propose(self, key: jax.Array, state: ModelEmitterState, repertoire: Repertoire, task: Task, params: Params,
                num: int) -> Proposal:
        propose = getattr(self.acquisition, "propose", None)
        if propose is not None:  # a source (Imagination) proposes by itself
            return propose(key, self, state, repertoire, task, params, num)
        pool_size = self.acquisition.pool_size(num)
        view = self.view(state, repertoire, task, params, num)
        with jax.named_scope("inner"):
            pool = self.inner.propose(key, state.inner, repertoire, task, params.part(params.emitter.inner),
                                      pool_size)
        pooled = {}
        for part in self.parts:
            with jax.named_scope(part.name):
                pool, pooled[part.name] = part.pool(key, state.parts[part.name], pool, view)
        with jax.named_scope("predict"):
            x = self.model.inputs(pool.actions, task)  # the pool's features computed here, once
            y, predicted = self.predicted(state, pool.actions, pool.parents, x, view)
            judgement = self._judgement(state, y, pool.actions, pool.parents, view)
        with jax.named_scope("acquire"):
            rows, rollout, discarded = contracts.selection(self.acquisition, self.acquisition.select(
                jax.random.fold_in(key, 5), state.acquisition, judgement, repertoire, pool.rollout,
                params.part(params.emitter.acquisition), num), num)
            if self.checks:
                contracts.values(self.acquisition, self.surrogate, rows, pool_size, y, view.warm_up)
            # During warm-up the pool's first rows as the inner emitter proposed them (the rule's choice unused).
            first = jnp.arange(num)
            rows = jnp.where(view.warm_up, first, rows).astype(jnp.int32)
            rollout = jnp.where(view.warm_up, pool.rollout[first], rollout)
            discarded = jnp.where(view.warm_up, 0, discarded).astype(jnp.int32)
            share = parts.model_share(self.parts, state.parts)
            from_model = jnp.ones(num, bool)
            if share is not None:
                rows, rollout, from_model = _share(rows, pool.rollout, share, view.warm_up, num)
        # The kept rows' predicted distances (the opener AUC's score) searched for them alone, as judgement.distance
        # would give them: a rule that reads no distances (Budgeted) then does not pay for a search of the pool.
        kept_sq, _ = repertoire_lib.k_nearest(repertoire, judgement.behaviors[rows], 1)
        info = ModelInfo(parts.kept(pool.info, rows, pool_size), judgement.behaviors[rows], jnp.sqrt(kept_sq[:, 0]),
                         from_model, discarded, None if judgement.validity is None else judgement.validity[rows],
                         {name: parts.kept((pooled[name], predicted[name]), rows, pool_size) for name in pooled},
                         None if pool.parents is None else pool.parents[rows])
        return Proposal(pool.actions[rows], rollout, info, None if pool.parents is None else pool.parents[rows],
                        x[rows, task.action_dim:] if self.keeps_features(task) else None)

    def update(self, key: jax.Array, state: ModelEmitterState, proposal: Proposal, evaluated: Evaluated,
               repertoire: Repertoire, task: Task, params: Params) -> tuple[ModelEmitterState, dict[str, jax.Array]]:
        info: ModelInfo = proposal.info
        evaluations = state.evaluations + proposal.rollout.sum(dtype=jnp.int32)
        own = params.emitter.surrogate
        surrogate = self.model.observe(key, state.surrogate, proposal.actions, proposal.rollout, evaluated, task, own,
                                       proposal.features)
        with jax.named_scope("train"):
            surrogate, loss = jax.lax.cond(evaluations >= self.warmup_samples,
                                           lambda: self.model.fit(key, surrogate, repertoire, task, own),
                                           lambda: (surrogate, jnp.float32(jnp.nan)))
        rule = acquisition.updated_state(self.acquisition, jax.random.fold_in(key, 5), state.acquisition, proposal,
                                         evaluated)
        inner, inner_metrics = self.inner.update(jax.random.fold_in(key, 1), state.inner,
                                                 Proposal(proposal.actions, proposal.rollout, info.inner), evaluated,
                                                 repertoire, task, params.part(params.emitter.inner))
        chain, chain_metrics = parts.updated(self.parts, state.parts, info.parts, proposal, evaluated,
                                             state.evaluations < self.warmup_samples)
        metrics = {"discarded": info.discarded, "model_loss": loss,
                   "prediction_error": prediction_error(info.predicted_behaviors, evaluated),
                   "opener_auc": opener_auc(info.predicted_distance, evaluated), **inner_metrics, **chain_metrics,
                   **self.model.report(info.validity, proposal.rollout, evaluated),
                   **({"model_share": info.from_model.mean(dtype=jnp.float32)} if parts.shared(self.parts) else {})}
        return ModelEmitterState(surrogate=surrogate, inner=inner, evaluations=evaluations, acquisition=rule,
                                 parts=chain), metrics

    def problems(self, metrics: Mapping[str, np.ndarray]) -> list[str]:
        """A model whose predictions were not finite: `prediction_error` NaN or infinite in a generation with
        usable rollouts (it is NaN only without any), what a surrogate that predicts NaN does silently unless
        `checks`."""
        usable = np.asarray(metrics["evaluations"]) - np.asarray(metrics["invalid"]) > 0
        broken = usable & ~np.isfinite(np.asarray(metrics["prediction_error"]))
        if not broken.any():
            return []
        return [f"the model's predictions ({type(self.surrogate).__name__}) were not finite in {int(broken.sum())} of "
                f"{int(usable.sum())} generations with usable rollouts (prediction_error NaN or infinite): its "
                "choice of candidates is blind; ModelEmitter(checks=True) stops the run at the first such "
                "prediction, naming the part"]

    def metrics(self) -> dict[str, Any]:
        own = {**_METRICS, **({"model_share": jnp.float32} if parts.shared(self.parts) else {}), **self.model.metrics()}
        for part in self.parts:
            own.update(part.metrics())
        return {**own, **self.inner.metrics()}


def judged(model: Any, surrogate: Any, y: jax.Array, repertoire: Repertoire, actions: jax.Array, task: Task,
           parents: jax.Array | None, warm_up: jax.Array, k: int) -> acquisition.Judged:
    """`Judged` from the members' predictions y [E, N, d + 1] of actions [N, n] and their parents' slots [N]
    (-1: none) or None, by `model` (`protocol.hooks`) with state `surrogate`; k: the neighbours of novelty."""
    mean = y.mean(axis=0)
    behaviors, qualities = mean[:, :-1], mean[:, -1]
    spread = jnp.sqrt(((y[..., :-1] - behaviors) ** 2).mean(axis=(0, 2)))
    # Two searches, so that XLA drops the one whose results the rule does not read: on a pool of 800 the
    # K nearest skills (novelty, improvement, neighbours) cost 1.5-5x the nearest one (distance, its quality).
    sq, slots = repertoire_lib.k_nearest(repertoire, behaviors, k)
    nearest_sq, nearest = repertoire_lib.k_nearest(repertoire, behaviors, 1)
    nearest_quality = jnp.where(nearest[:, 0] >= 0, repertoire.qualities[jnp.maximum(nearest[:, 0], 0)], 0.0)
    novelty, improvement = acquisition.scores_of_neighbours(sq, slots, qualities, repertoire)
    validity = model.usable(surrogate, actions, task)
    parent_novelty = None if parents is None else jnp.where(
        parents >= 0, repertoire.novelty[jnp.maximum(parents, 0)], jnp.nan)
    return acquisition.Judged(behaviors, qualities, spread, jnp.sqrt(nearest_sq[:, 0]), nearest_quality, novelty,
                              improvement, jnp.sqrt(sq), validity, parent_novelty, y, warm_up, parents)


def _share(rows: jax.Array, wanted: jax.Array, share: jax.Array, warm_up: jax.Array,
           num: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The fallback's rows [num]: the rule's first round(share * num) rows (all during warm-up), then the pool's
    first rows not among them (the inner emitter's own order); their rollout mask [num] and which came from the
    rule [num]."""
    slots = jnp.arange(num)
    from_model = warm_up | (slots < jnp.round(share * num))
    taken = jnp.zeros(wanted.shape[0], bool).at[rows].set(from_model)  # a rule's rows are distinct
    untaken_first = jnp.argsort(taken, stable=True)  # untaken rows in pool order, then the taken ones
    fill = untaken_first[jnp.maximum(slots - from_model.sum(), 0)]
    rows = jnp.where(from_model, rows, fill).astype(jnp.int32)
    return rows, wanted[rows], from_model


def opener_auc(score: jax.Array, evaluated: Evaluated) -> jax.Array:
    """P(score of a usable rollout that opened a niche > score of one that did not), ties 1/2; NaN without both.

    score [P] (the model's: its predicted distance to the nearest skill); `evaluated` of the same P rows. NaN
    scores count as the lowest.
    """
    opened = evaluated.usable & (evaluated.status == AddStatus.ADDED)
    return auc(score, opened, evaluated.usable & ~opened)
