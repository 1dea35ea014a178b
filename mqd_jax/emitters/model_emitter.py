"""M-QD's model as an emitter wrapper: a learned forward model decides which of another emitter's candidates
are worth a rollout (paper, "Model-Based Quality-Diversity Search", Algorithm 1).

`ModelEmitter(inner, acquisition, surrogate)` asks `inner` for a pool of candidates,
predicts their behaviors and qualities with its surrogate (any part that keeps the protocol of
`mqd_jax.surrogate.protocol`; the built-in `mqd_jax.surrogate.surrogate.Surrogate`: one network or a
vmapped ensemble, its training data, features, gate and validity classifier), anchors the predictions
where `anchoring` says (`mqd_jax.emitters.anchoring`), scores them against the repertoire and lets
the acquisition rule choose (`mqd_jax.emitters.acquisition`: the paper's `Threshold`
filter, `Budgeted` ranking or `Diverse` batch selection). Until
`warmup_samples` of its candidates were rolled out it rolls out the inner
emitter's proposal as it came (the rule's choice is not used). After every generation past warm-up it fits
the surrogate (`fit`); the built-in one also `observe`s every generation's rollouts. It owns the
surrogate's state, measures its held-out error and reports the model's metrics; any emitter can be the inner
one.

Two options change what the model's choice is worth (`anchoring` changes what it says):

* `fallback` (`Fallback`): a share of each generation's rollouts goes to the
  model's choice and the rest to the inner emitter's own first candidates; the
  share pursues whichever side's rollouts have recently opened new niches
  more often (adaptive pursuit), so a model that does not
  help costs at most the floor's share of the rollouts.

And one changes what the model is asked about: `steering` (`steering.Steering`)
replaces the last rows of the inner emitter's pool with children the model's
Jacobian aims at empty behavior space. The inner emitter's `update` then sees
its proposal with those rows' actions replaced (IsoLine and Uniform keep no
per-candidate state); the fallback's rows are always the inner emitter's own.

And the surrogate's `validity` (`validity.Validity`) adds a classifier of usable
rollouts, whose judgement the acquisition rules read: candidates judged likely
invalid come after the others.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import pytree
from mqd_jax.core import repertoire as repertoire_lib
from mqd_jax.core.checks import is_int
from mqd_jax.core.emitter import Emitter, Evaluated, Proposal, init_emitter
from mqd_jax.core.params import Params, check_params_of, params_of
from mqd_jax.core.repertoire import AddStatus, Repertoire
from mqd_jax.core.task import Task
from mqd_jax.emitters import acquisition, anchoring, contracts
from mqd_jax.emitters import steering as steering_lib
from mqd_jax.emitters.anchoring import prediction_error
from mqd_jax.emitters.pursuit import Fallback
from mqd_jax.emitters.step_aside import StepAside, explained
from mqd_jax.surrogate import protocol
from mqd_jax.surrogate.surrogate import Surrogate

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
      fallback: `FallbackState`, or () without a fallback.
      steering: `pursuit.FallbackState` of a steering pursuit, or ().
      step_aside: `step_aside.StepAsideState`, or () without stepping aside.
      anchor_errors: anchoring "auto": [2] float32 averaged behavior MSE of the plain and the anchored
        predictions (NaN before the first); else ().
      acquisition: the rule's state (its `init`), or ().
    """

    surrogate: Any
    inner: Any
    evaluations: jax.Array
    fallback: Any = ()
    steering: Any = ()
    step_aside: Any = ()
    anchor_errors: Any = ()
    acquisition: Any = ()


@dataclasses.dataclass(frozen=True)
class ModelEmitter(Emitter):
    """Filters or ranks `inner`'s candidates with a learned forward model.

    Attributes:
      inner: the emitter whose candidates the model judges.
      acquisition: the rule that picks the candidates to roll out.
      surrogate: the model (`mqd_jax.surrogate.protocol`: any object with `init`, `fit` and `predict`; the
        built-in `Surrogate` with its training, features, gate and validity classifier).
      k: the repertoire neighbours the predicted novelty and improvement average over.
      warmup_samples: rollouts before the model is trained and used.
      fallback: a `Fallback`, or None to always follow the acquisition rule.
        Only with a ranking rule (`Budgeted`, `Diverse`), whose best rows come first.
      steering: a `steering.Steering`, or None for the inner emitter's pool alone. Only with a ranking rule
        whose pool holds more than the generation's rollouts besides the steered rows; off during warm-up. A
        child whose Jacobian is not finite (see `_steered`) is not steered: its row keeps the inner candidate.
      anchoring: "none", "always" or "auto"; anchor: "parent" or "nearest" (`mqd_jax.emitters.anchoring`).
      step_aside: a `StepAside`, or None: while the model's predictions explain no more of its rollouts'
        behaviors than chance, the generation is the inner emitter's own first candidates. Only with a ranking
        rule.
      checks: check the parts' values every generation as the program runs (`contracts.values`: the rule's rows
        in range and distinct, the surrogate's predictions finite after warm-up), stopping the run with an error
        that names the part; their shapes and dtypes are checked as it is traced, always.

    Metrics: `discarded` (candidates the model turned down), `model_loss`
    (mean training loss of the generation's mini-batches; NaN when it did not
    train), `prediction_error` (behavior MSE in real units of the predictions
    on this generation's usable rollouts, before training on them; NaN if
    none), `opener_auc` (among this generation's usable rollouts, the
    probability that one which opened a niche had a larger predicted distance
    to the nearest skill than one which did not; ties count 1/2; NaN without
    both kinds), with a
    fallback or `step_aside` `model_share` (the share of the generation's rows from the rule: 1 during warm-up),
    with steering `steered` (the generation's rollouts that were steered children) and, with its pursuit,
    `steering_share` (the pursuit's share of the steerable rows this generation), with `step_aside`
    `model_skill` (the averaged explained variance this generation's choice was made with; NaN before one),
    with validity
    `validity_auc` (among this generation's rollouts, the probability that a usable one had a higher predicted
    probability of being usable than an unusable one; ties 1/2; NaN without both), and the inner emitter's.
    """

    inner: Emitter
    acquisition: acquisition.Acquisition = dataclasses.field(default_factory=acquisition.Threshold)
    surrogate: Any = dataclasses.field(default_factory=Surrogate)
    k: int = 5
    warmup_samples: int = 0
    fallback: Fallback | None = None
    steering: steering_lib.Steering | None = None
    anchoring: str = "none"
    anchor: str = "parent"
    step_aside: StepAside | None = None
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
        if self.anchoring not in anchoring.ANCHORING:
            raise ValueError(f"ModelEmitter.anchoring={self.anchoring!r} is invalid: expected one of "
                             f"{anchoring.ANCHORING}")
        if self.anchor not in anchoring.ANCHORS:
            raise ValueError(f"ModelEmitter.anchor={self.anchor!r} is invalid: expected one of {anchoring.ANCHORS}")
        if not isinstance(self.checks, bool):
            raise ValueError(f"ModelEmitter.checks={self.checks!r} is invalid: expected a bool")
        for name, lowest in (("k", 1), ("warmup_samples", 0)):
            value = getattr(self, name)
            if not (is_int(value) and value >= lowest):
                raise ValueError(f"ModelEmitter.{name}={value!r} is invalid: expected an int >= {lowest}")
        ranked = acquisition.is_ranked(self.acquisition)
        unranked = "not one whose rows are not ranked, as Threshold's"
        for name, kind, why in (("fallback", Fallback, unranked), ("step_aside", StepAside, unranked),
                                ("steering", steering_lib.Steering, "Threshold would roll out every steered child")):
            part = getattr(self, name)
            if part is not None and not (isinstance(part, kind) and ranked):
                raise ValueError(f"ModelEmitter.{name}={part!r} is invalid: expected None, or a {kind.__name__} "
                                 f"with a ranking acquisition rule ({why})")
        clash = set(self._own_metrics()) & set(self.inner.metrics())
        if clash:
            raise ValueError(f"ModelEmitter: the inner emitter's metrics {sorted(clash)} clash with the model's")

    @property
    def model(self) -> Any:
        """The surrogate as this emitter reads it: the built-in `Surrogate` itself, any other with the neutral
        hooks of `protocol.Hooks`."""
        return protocol.hooks(self.surrogate)

    def default_params(self) -> ModelEmitterParams:
        return ModelEmitterParams(self.model.default_params(), self.inner.default_params(),
                                  params_of(self.acquisition))

    def check_params(self, params: ModelEmitterParams) -> None:
        self.model.check_params(params.surrogate)
        self.inner.check_params(params.inner)
        check_params_of(self.acquisition, params.acquisition)

    def check_run(self, population_size: int, max_generations: int) -> None:
        self.inner.check_run(self.acquisition.pool_size(population_size), max_generations)
        budget = population_size * max_generations
        if self.warmup_samples >= budget:
            raise ValueError(f"ModelEmitter.warmup_samples={self.warmup_samples} is invalid for this run: expected "
                             f"fewer than its population_size x max_generations ({budget}) rollouts, or the model "
                             "is never used")
        if self.steering is not None:
            self._steered_count(self.acquisition.pool_size(population_size), population_size)

    def pool_size(self, num: int) -> int:
        return self.inner.pool_size(self.acquisition.pool_size(num))

    def keeps_features(self, task: Task) -> bool:
        """The model takes the task's features (`Surrogate(features=True)` and the task has some): the repertoire
        keeps each skill's, so that anchors and training rows read them rather than compute them again."""
        return self.model.featured(task)

    def check_task(self, task: Task) -> None:
        self.inner.check_task(task)
        self.model.check_task(task)

    def _steered_count(self, pool_size: int, num: int) -> int:
        """The rows steering replaces in a pool of `pool_size` for `num` rollouts; ValueError unless at least 1,
        leaving `num` to the inner emitter."""
        count = self.steering.count(pool_size)
        if not 1 <= count <= pool_size - num:
            raise ValueError(f"ModelEmitter.steering={self.steering!r} steers {count} of a pool of {pool_size}: "
                             f"expected at least 1, leaving the inner emitter at least the {num} rollouts of a "
                             "generation (a smaller share, or a larger pool)")
        return count

    def init(self, key: jax.Array, task: Task, capacity: int) -> ModelEmitterState:
        """The state before any rollout; `capacity`: the repertoire's (the run passes its `Config.capacity`)."""
        return ModelEmitterState(surrogate=self.model.init(key, task, capacity),
                                 inner=init_emitter(self.inner, jax.random.fold_in(key, 1), task, capacity),
                                 evaluations=jnp.int32(0),
                                 fallback=() if self.fallback is None else self.fallback.init(),
                                 steering=() if self._steering_pursuit is None else self._steering_pursuit.init(),
                                 step_aside=() if self.step_aside is None else self.step_aside.init(),
                                 anchor_errors=anchoring.init(self.anchoring),
                                 acquisition=acquisition.state_of(self.acquisition, jax.random.fold_in(key, 5), task))

    def judge(self, state: ModelEmitterState, actions: jax.Array, repertoire: Repertoire, task: Task,
              parents: jax.Array | None = None) -> acquisition.Judged:
        """The model's view of actions [N, n] (with their parents' slots [N], or None) against the repertoire
        (anchored as `anchoring` and `anchor` say)."""
        plain, anchored = self.predictions(state, actions, repertoire, task, parents)
        return self._judged(state, plain, anchored, repertoire, actions, task, parents)

    def predictions(self, state: ModelEmitterState, actions: jax.Array, repertoire: Repertoire, task: Task,
                    parents: jax.Array | None = None,
                    x: jax.Array | None = None) -> tuple[jax.Array, jax.Array | None]:
        """The surrogate's plain and anchored predictions [E, N, d + 1] of actions [N, n] (`anchoring.predictions`;
        x: their inputs where computed)."""
        return anchoring.predictions(self.model, state.surrogate, actions, repertoire, task, self.anchoring,
                                     self.anchor, parents, x)

    def chosen(self, state: ModelEmitterState, plain: jax.Array, anchored: jax.Array | None) -> jax.Array:
        """The predictions [E, N, d + 1] `anchoring` trusts now (`anchoring.chosen`)."""
        return anchoring.chosen(self.anchoring, state.anchor_errors, plain, anchored)

    def _judged(self, state: ModelEmitterState, plain: jax.Array, anchored: jax.Array | None,
                repertoire: Repertoire, actions: jax.Array, task: Task,
                parents: jax.Array | None) -> acquisition.Judged:
        """`Judged` from the members' plain and anchored predictions [E, N, d + 1] of actions [N, n] and their
        parents' slots [N] (-1: none) or None."""
        y = self.chosen(state, plain, anchored)
        mean = y.mean(axis=0)
        behaviors, qualities = mean[:, :-1], mean[:, -1]
        spread = jnp.sqrt(((y[..., :-1] - behaviors) ** 2).mean(axis=(0, 2)))
        # Two searches, so that XLA drops the one whose results the rule does not read: on a pool of 800 the
        # K nearest skills (novelty, improvement, neighbours) cost 1.5-5x the nearest one (distance, its quality).
        sq, slots = repertoire_lib.k_nearest(repertoire, behaviors, self.k)
        nearest_sq, nearest = repertoire_lib.k_nearest(repertoire, behaviors, 1)
        nearest_quality = jnp.where(nearest[:, 0] >= 0, repertoire.qualities[jnp.maximum(nearest[:, 0], 0)], 0.0)
        novelty, improvement = acquisition.scores_of_neighbours(sq, slots, qualities, repertoire)
        distances = jnp.sqrt(sq)
        validity = self.model.usable(state.surrogate, actions, task)
        parent_novelty = None if parents is None else jnp.where(
            parents >= 0, repertoire.novelty[jnp.maximum(parents, 0)], jnp.nan)
        return acquisition.Judged(behaviors, qualities, spread, jnp.sqrt(nearest_sq[:, 0]), nearest_quality, novelty,
                                  improvement, distances, validity, parent_novelty)

    def propose(self, key: jax.Array, state: ModelEmitterState, repertoire: Repertoire, task: Task, params: Params,
                num: int) -> Proposal:
        pool_size = self.acquisition.pool_size(num)
        with jax.named_scope("inner"):
            pool = self.inner.propose(key, state.inner, repertoire, task, params.part(params.emitter.inner),
                                      pool_size)
        warm_up = state.evaluations < self.warmup_samples
        if self.steering is not None:
            with jax.named_scope("steer"):
                pool, steered = self._steered(jax.random.fold_in(key, 2), state, pool, repertoire, task, params, num,
                                              warm_up)
        with jax.named_scope("predict"):
            x = self.model.inputs(pool.actions, task)  # the pool's features computed here, once
            plain, anchored = self.predictions(state, pool.actions, repertoire, task, pool.parents, x)
            judged = self._judged(state, plain, anchored, repertoire, pool.actions, task, pool.parents)
        with jax.named_scope("acquire"):
            rows, rollout, discarded = contracts.selection(self.acquisition, self.acquisition.select(
                jax.random.fold_in(key, 5), state.acquisition, judged, repertoire, pool.rollout,
                params.part(params.emitter.acquisition), num), num)
            if self.checks:
                contracts.values(self.acquisition, self.surrogate, rows, pool_size, plain, warm_up)
            # During warm-up the pool's first rows as the inner emitter proposed them (the rule's choice unused).
            first = jnp.arange(num)
            rows = jnp.where(warm_up, first, rows).astype(jnp.int32)
            rollout = jnp.where(warm_up, pool.rollout[first], rollout)
            discarded = jnp.where(warm_up, 0, discarded).astype(jnp.int32)
            from_model = jnp.ones(num, bool)
            if self.fallback is not None or self.step_aside is not None:
                share = jnp.float32(1.0) if self.fallback is None else state.fallback.share
                if self.step_aside is not None:  # a model at chance chooses none
                    share = jnp.where(self.step_aside.trusts(state.step_aside), share, 0.0)
                rows, rollout, from_model = _share(rows, pool.rollout, share, warm_up, num)
        keep = lambda x: x[rows] if jnp.ndim(x) and jnp.shape(x)[0] == pool_size else x  # noqa: E731
        # The kept rows' predicted distances (the opener AUC's score) searched for them alone, as judged.distance
        # would give them: a rule that reads no distances (Budgeted) then does not pay for a search of the pool.
        kept_sq, _ = repertoire_lib.k_nearest(repertoire, judged.behaviors[rows], 1)
        info = {"inner": jax.tree.map(keep, pool.info), "predicted_behaviors": judged.behaviors[rows],
                "predicted_distance": jnp.sqrt(kept_sq[:, 0]), "from_model": from_model, "discarded": discarded}
        if self.steering is not None:
            info["steered"] = steered[rows] & rollout
        if self.model.validity is not None:
            info["validity"] = judged.validity[rows]
        if self.anchoring == "auto":  # both predictions of the kept rows, for the held-out errors
            info["both_behaviors"] = jnp.stack([plain[:, rows].mean(0)[:, :-1], anchored[:, rows].mean(0)[:, :-1]])
        return Proposal(pool.actions[rows], rollout, info, None if pool.parents is None else pool.parents[rows],
                        x[rows, task.action_dim:] if self.keeps_features(task) else None)

    def _steered(self, key: jax.Array, state: ModelEmitterState, pool: Proposal, repertoire: Repertoire, task: Task,
                 params: Params, num: int, warm_up: jax.Array) -> tuple[Proposal, jax.Array]:
        """The pool [P] with its last rows replaced by steered children (not during warm-up or while the repertoire
        is empty; their `parents` by the steering parents where the pool names parents), and which rows [P]
        were."""
        pool_size = pool.actions.shape[0]
        count = self._steered_count(pool_size, num)
        # Reverse mode where the behavior has fewer dimensions than the action (d VJPs rather than n JVPs: 4x
        # faster through PushCube's IK). Reverse mode turns a masked branch's NaN (a norm's gradient at 0 under a
        # `where`) into a NaN Jacobian where forward mode does not: a child that is not finite is not steered, its
        # row keeps the inner emitter's candidate.
        differentiate = jax.jacrev if task.behavior_dim < task.action_dim else jax.jacfwd
        jacobian = jax.vmap(differentiate(lambda a: self.model.predict(state.surrogate, a, task)[0]))
        quality_gradient = jax.vmap(jax.grad(lambda a: self.model.predict(state.surrogate, a, task)[1]))
        children, steering_parents = self.steering.steer(key, repertoire, jacobian, task, params, count,
                                                         quality_gradient)
        on = ~warm_up & (repertoire.count > 0)
        steered_rows = count if self._steering_pursuit is None else jnp.round(state.steering.share * count)
        finite = jnp.zeros(pool_size, bool).at[pool_size - count:].set(jnp.isfinite(children).all(axis=1))
        steered = on & finite & (jnp.arange(pool_size) >= pool_size - steered_rows)

        def spliced(rows: jax.Array, steered_values: jax.Array) -> jax.Array:
            """rows [P, ...] with the steered ones among the last `count` taken from steered_values [count, ...]."""
            on_tail = steered[pool_size - count:].reshape((count,) + (1,) * (rows.ndim - 1))
            return rows.at[pool_size - count:].set(jnp.where(on_tail, steered_values, rows[pool_size - count:]))

        parents = None if pool.parents is None else spliced(pool.parents, steering_parents)
        return pool.replace(actions=spliced(pool.actions, children), parents=parents), steered

    def update(self, key: jax.Array, state: ModelEmitterState, proposal: Proposal, evaluated: Evaluated,
               repertoire: Repertoire, task: Task, params: Params) -> tuple[ModelEmitterState, dict[str, jax.Array]]:
        evaluations = state.evaluations + proposal.rollout.sum(dtype=jnp.int32)
        own = params.emitter.surrogate
        surrogate = self.model.observe(key, state.surrogate, proposal.actions, proposal.rollout, evaluated, task, own,
                                       proposal.features)
        with jax.named_scope("train"):
            surrogate, loss = jax.lax.cond(evaluations >= self.warmup_samples,
                                           lambda: self.model.fit(key, surrogate, repertoire, task, own),
                                           lambda: (surrogate, jnp.float32(jnp.nan)))
        anchor_errors = state.anchor_errors
        if self.anchoring == "auto":
            anchor_errors = anchoring.averaged(anchor_errors, proposal.info["both_behaviors"], evaluated)
        rule = acquisition.updated_state(self.acquisition, jax.random.fold_in(key, 5), state.acquisition, proposal,
                                         evaluated)
        inner_proposal = Proposal(proposal.actions, proposal.rollout, proposal.info["inner"])
        inner, inner_metrics = self.inner.update(jax.random.fold_in(key, 1), state.inner, inner_proposal, evaluated,
                                                 repertoire, task, params.part(params.emitter.inner))
        metrics = {"discarded": proposal.info["discarded"], "model_loss": loss,
                   "prediction_error": prediction_error(proposal.info["predicted_behaviors"], evaluated),
                   "opener_auc": opener_auc(proposal.info["predicted_distance"], evaluated), **inner_metrics}
        fallback, was_warm_up = state.fallback, state.evaluations < self.warmup_samples
        if self.fallback is not None or self.step_aside is not None:
            metrics["model_share"] = proposal.info["from_model"].mean(dtype=jnp.float32)
        if self.fallback is not None:
            fallback = jax.lax.cond(was_warm_up, lambda: state.fallback,
                                    lambda: self.fallback.update(state.fallback, proposal.info["from_model"],
                                                                 evaluated))
        if self.model.validity is not None:
            metrics["validity_auc"] = auc(proposal.info["validity"], proposal.rollout & evaluated.usable,
                                          proposal.rollout & ~evaluated.usable)
        step_aside = state.step_aside
        if self.step_aside is not None:
            metrics["model_skill"] = state.step_aside.skill
            skill = explained(proposal.info["predicted_behaviors"], evaluated)
            step_aside = jax.lax.cond(was_warm_up, lambda: state.step_aside,
                                      lambda: self.step_aside.update(state.step_aside, skill))
        steering = state.steering
        if self.steering is not None:
            metrics["steered"] = proposal.info["steered"].sum(dtype=jnp.int32)
        if self._steering_pursuit is not None:
            metrics["steering_share"] = state.steering.share
            steering = jax.lax.cond(was_warm_up, lambda: state.steering,
                                    lambda: self._steering_pursuit.update(state.steering, proposal.info["steered"],
                                                                          evaluated))
        return ModelEmitterState(surrogate=surrogate, inner=inner, evaluations=evaluations, fallback=fallback,
                                 steering=steering, step_aside=step_aside, anchor_errors=anchor_errors,
                                 acquisition=rule), metrics

    def _own_metrics(self) -> dict[str, Any]:
        shared = self.fallback is not None or self.step_aside is not None
        return {**_METRICS, **({"model_share": jnp.float32} if shared else {}),
                **({} if self.steering is None else {"steered": jnp.int32}),
                **({} if self.step_aside is None else {"model_skill": jnp.float32}),
                **({} if self._steering_pursuit is None else {"steering_share": jnp.float32}),
                **({} if self.model.validity is None else {"validity_auc": jnp.float32})}

    @property
    def _steering_pursuit(self) -> Fallback | None:
        return None if self.steering is None else self.steering.pursuit

    def metrics(self) -> dict[str, Any]:
        return {**self._own_metrics(), **self.inner.metrics()}


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


def auc(score: jax.Array, positive: jax.Array, negative: jax.Array) -> jax.Array:
    """P(score of a positive row > score of a negative one) over score [P] and the masks [P], ties 1/2; NaN
    without both kinds. NaN scores count as the lowest."""
    score = jnp.nan_to_num(score, nan=-jnp.inf)
    pairs = positive[:, None] & negative[None, :]
    wins = jnp.where(score[:, None] > score[None, :], 1.0, jnp.where(score[:, None] == score[None, :], 0.5, 0.0))
    n = pairs.sum()
    return jnp.where(n > 0, jnp.where(pairs, wins, 0.0).sum() / jnp.maximum(n, 1), jnp.nan)
