"""Acquisition rules: which of a pool of candidates a model-based emitter rolls out.

From the model's predicted behavior b~ and quality q~ of a candidate, and the K
repertoire skills nearest to b~ in behavior space (paper, "Model-Based
Quality-Diversity Search"):

    predicted novelty             nov~ = mean_i ||b_nn_i - b~||
    predicted quality improvement qua~ = mean_i (q~ - q_nn_i)

With fewer than K skills in the repertoire the means run over those there are;
with none, both scores are +inf. `Judged` holds these with the predictions and
the ensemble's spread. A rule is a frozen dataclass with `pool_size(num)` (how
many candidates it wants to choose `num` from) and `select`, used by
`mqd_jax.emitters.model_emitter.ModelEmitter`:

* `Threshold`: the paper's Algorithm 1 filter;
* `Budgeted`: a fixed number from the top of a ranked pool;
* `Diverse` (`mqd_jax.emitters.diverse`): a fixed number chosen one at a time
  by optimistic (UCB) gain against an imagined repertoire that already holds
  the predicted behaviors of those chosen, so one generation does not spend
  rollouts on near-duplicates.

Ranking rules return their rows best first (`ModelEmitter`'s fallback keeps a
prefix of them). With a validity classifier (`mqd_jax.surrogate.validity`), the rules
read its judgement: `Threshold` rolls out none of the candidates it judges
likely unusable (probability below `PLAUSIBLE`), `Budgeted` and `Diverse`
rank them after the likely usable ones of their tier (a candidate predicted
novel still comes before one that is not: it may open a niche, the other
cannot).
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import pytree
from mqd_jax.core import repertoire as repertoire_lib
from mqd_jax.core.checks import check_traced, is_int, is_real
from mqd_jax.core.params import Params
from mqd_jax.core.repertoire import Repertoire

# A candidate whose probability of a usable rollout is below this is judged likely unusable.
PLAUSIBLE = 0.5


def predicted_scores(pred_behaviors: jax.Array, pred_qualities: jax.Array, rep: Repertoire,
                     k: int) -> tuple[jax.Array, jax.Array]:
    """nov~ [P] and qua~ [P] of predictions pred_behaviors [P, d], pred_qualities [P]."""
    return scores_of_neighbours(*repertoire_lib.k_nearest(rep, pred_behaviors, k), pred_qualities, rep)


def scores_of_neighbours(sq: jax.Array, slots: jax.Array, pred_qualities: jax.Array,
                         rep: Repertoire) -> tuple[jax.Array, jax.Array]:
    """nov~ [P] and qua~ [P] from each prediction's K nearest skills (`repertoire.k_nearest`: squared distances
    [P, K], slots [P, K], -1 where missing) and its predicted quality [P]."""
    found = slots >= 0
    n = found.sum(1)
    mean = lambda x: jnp.where(n > 0, jnp.where(found, x, 0.0).sum(1) / jnp.maximum(n, 1), jnp.inf)  # noqa: E731
    novelty = mean(jnp.sqrt(jnp.where(found, sq, 0.0)))
    improvement = mean(pred_qualities[:, None] - rep.qualities[jnp.maximum(slots, 0)])
    return novelty, improvement


@pytree.dataclass
class Judged:
    """The model's view of a pool of N candidates.

    Attributes:
      behaviors: [N, d] predicted behaviors b~ (real units).
      qualities: [N] predicted qualities q~.
      spread: [N] the ensemble's disagreement on the behavior: the root mean
        square over members and axes of a member's behavior minus b~ (0 for a
        single network).
      distance: [N] from b~ to the nearest repertoire skill's behavior (inf if none).
      nearest_quality: [N] that skill's quality (0 if none).
      novelty: [N] nov~; improvement: [N] qua~ (`predicted_scores`).
      neighbours: [N, K] distances from b~ to its K nearest skills, ascending
        (inf where fewer exist; its first column is `distance`), or None.
        `ModelEmitter` finds the nearest skill (distance, nearest_quality) and
        the K nearest (novelty, improvement, neighbours) by two searches, so
        that a rule reading none of one's fields costs nothing of it (XLA
        drops unused work: `Diverse` with one neighbour reads the first only).
      validity: [N] the probability of a usable rollout (`mqd_jax.surrogate.validity`), or None (all judged usable).
      parent_novelty: [N] the repertoire's novelty of each candidate's parent (the skill it was varied from; NaN
        for a candidate without one), or None where the inner emitter names no parents.
      members: [E, N, d + 1] each member's predicted behaviors and quality (an ensemble's E members; E = 1 for a
        single network), as the chain's predict stages leave them: what a rule that samples a member (Thompson
        sampling) reads. None where whoever judged did not say.
      warm_up: bool scalar, the emitter is still warming up (its rule's choice is not used this generation,
        and the model has not trained), or None where whoever judged did not say.
      parents: [N] int32 each candidate's parent's slot (-1: none), or None where the inner emitter names no
        parents or whoever judged did not say.
    """

    behaviors: jax.Array
    qualities: jax.Array
    spread: jax.Array
    distance: jax.Array
    nearest_quality: jax.Array
    novelty: jax.Array
    improvement: jax.Array
    neighbours: jax.Array | None = None
    validity: jax.Array | None = None
    parent_novelty: jax.Array | None = None
    members: jax.Array | None = None
    warm_up: jax.Array | None = None
    parents: jax.Array | None = None

    @property
    def plausible(self) -> jax.Array:
        """[N] bool: judged likely usable (probability >= `PLAUSIBLE`; all without a validity judgement)."""
        if self.validity is None:
            return jnp.ones(self.novelty.shape, bool)
        return self.validity >= PLAUSIBLE


def passes(novelty: jax.Array, improvement: jax.Array, t_nov: jax.Array, t_qua: jax.Array) -> jax.Array:
    """[P] bool: Algorithm 1's test, nov~ > t_nov or qua~ > t_qua. NaN predictions fail it."""
    return (novelty > t_nov) | (improvement > t_qua)


def ranking(novelty: jax.Array, improvement: jax.Array, t_nov: jax.Array, wanted: jax.Array,
            plausible: jax.Array | None = None) -> jax.Array:
    """[N] candidate indices, most promising first.

    First the `wanted` [N] candidates (those the inner emitter would roll out),
    among them the ones with nov~ > t_nov, then the rest; within each, first
    the `plausible` [N] ones (judged likely usable; all if None); the novel
    ones by descending nov~, the rest by descending qua~. Ties go to the
    higher qua~, then the lower index; NaN scores come last.
    """
    novel = novelty > t_nov
    primary = jnp.where(novel, novelty, improvement)
    plausible = jnp.ones_like(wanted) if plausible is None else plausible
    # lexsort: the last key is the primary one; ascending, so negate; NaN sorts last.
    return jnp.lexsort((-improvement, -primary, ~plausible, ~novel, ~wanted)).astype(jnp.int32)


@pytree.dataclass
class ThresholdParams:
    """The paper's thresholds, traced: predicted novelty `t_nov` and predicted quality improvement `t_qua`."""

    t_nov: jax.Array
    t_qua: jax.Array


@dataclasses.dataclass(frozen=True)
class Threshold:
    """The paper's filter (Algorithm 1): of `num` candidates, roll out those whose predicted novelty exceeds
    `t_nov` or whose predicted improvement exceeds `t_qua` (and are judged likely usable, with a validity
    classifier). `t_nov` (>= 0) and `t_qua` (any finite) are the defaults of its traced parameters
    (`ThresholdParams`; Table II: 0.04 and 0). Its rows are the pool's own, unranked (`ranked` False)."""

    ranked: ClassVar[bool] = False
    t_nov: float = 0.04
    t_qua: float = 0.0

    def __post_init__(self) -> None:
        _check_thresholds(self, ("t_nov", "t_qua"))

    def default_params(self) -> ThresholdParams:
        return ThresholdParams(jnp.float32(self.t_nov), jnp.float32(self.t_qua))

    def check_params(self, params: ThresholdParams) -> None:
        check_traced("Threshold.params", "t_nov", params.t_nov)
        check_traced("Threshold.params", "t_qua", params.t_qua, lowest=-np.inf)

    def pool_size(self, num: int) -> int:
        return num

    def select(self, key: jax.Array, state: Any, judged: Judged, repertoire: Repertoire, wanted: jax.Array,
               params: Params, num: int) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Rows [num] of the pool kept, their rollout mask [num] and how many wanted candidates were turned down."""
        own = params.emitter
        rollout = wanted & passes(judged.novelty, judged.improvement, own.t_nov, own.t_qua) & judged.plausible
        return jnp.arange(num), rollout, (wanted & ~rollout).sum(dtype=jnp.int32)


def _check_thresholds(rule: object, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(rule, name)
        lowest = -np.inf if name == "t_qua" else 0.0
        if not (is_real(value) and value >= lowest):
            expected = "a finite float" if name == "t_qua" else "a finite float >= 0"
            raise ValueError(f"{type(rule).__name__}.{name}={value!r} is invalid: expected {expected}")


@pytree.dataclass
class BudgetedParams:
    """Budgeted's traced parameter: the predicted novelty `t_nov` above which a candidate ranks as novel."""

    t_nov: jax.Array


@dataclasses.dataclass(frozen=True)
class Budgeted:
    """Budgeted ranking: rank `pool_factor` x num candidates (`ranking`, novel above the traced `t_nov`, its
    default the field `t_nov`) and roll out the top num."""

    pool_factor: int = 4
    t_nov: float = 0.04

    def __post_init__(self) -> None:
        check_pool_factor(self)
        _check_thresholds(self, ("t_nov",))

    def default_params(self) -> BudgetedParams:
        return BudgetedParams(jnp.float32(self.t_nov))

    def check_params(self, params: BudgetedParams) -> None:
        check_traced("Budgeted.params", "t_nov", params.t_nov)

    def pool_size(self, num: int) -> int:
        return num * self.pool_factor

    def select(self, key: jax.Array, state: Any, judged: Judged, repertoire: Repertoire, wanted: jax.Array,
               params: Params, num: int) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Rows [num] of the pool kept (best first), their rollout mask [num] and how many candidates were turned
        down."""
        top = ranking(judged.novelty, judged.improvement, params.emitter.t_nov, wanted, judged.plausible)[:num]
        return ranked_result(top, wanted)


def ranked_result(top: jax.Array, wanted: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """A ranking rule's result from its rows `top` [num] of a pool whose rollout mask is `wanted` [N]: the rows,
    their rollout mask and the count of the pool's other rows (turned down)."""
    return top, wanted[top], jnp.int32(wanted.shape[0] - top.shape[0])


def check_pool_factor(rule: object) -> None:
    value = rule.pool_factor
    if not (is_int(value) and value >= 1):
        raise ValueError(f"{type(rule).__name__}.pool_factor={value!r} is invalid: expected an int >= 1")


class Acquisition(Protocol):
    """What `ModelEmitter` needs of a rule (`Threshold`, `Budgeted` and `Diverse`; a user's own is another).

    The contract of `select(key, state, judged, repertoire, wanted, params, num)`:

    * it gets a key of its own (a stochastic rule draws from it), its state (`init`'s, else ()), the model's
      view of a pool of N = `pool_size(num)` candidates (`Judged`), the repertoire and the inner emitter's
      rollout mask `wanted` [N];
    * it returns the rows [num] of the pool it keeps, *distinct*, their rollout mask [num] (normally
      `wanted[rows]`: a row the inner emitter did not want must not be rolled out) and the int32 count of
      candidates the model turned down (a metric, `discarded`);
    * a ranking rule returns its rows best first: a `Fallback` keeps only the first round(share x num) of them
      and fills the rest with the inner emitter's own first candidates. A rule whose rows are not a ranking
      sets the class attribute `ranked = False` (as `Threshold`), and a fallback or steering is refused with it;
    * it need not handle warm-up: until `ModelEmitter.warmup_samples` rollouts, the emitter rolls out the
      pool's first num rows as the inner emitter proposed them and does not use the rule's choice.

    Optionally, as an `Emitter` has: `default_params()` and `check_params(params)` (traced parameters, read as
    `params.emitter` in `select`); `init(key, task)` (a state, else ()) and `update(key, state, proposal,
    evaluated)` (the state after the generation's rollouts: `proposal` is the emitter's, its `info` holding
    the kept rows' `predicted_behaviors`).
    """

    def pool_size(self, num: int) -> int:
        """How many candidates the rule chooses `num` from."""

    def select(self, key: jax.Array, state: Any, judged: Judged, repertoire: Repertoire, wanted: jax.Array,
               params: Params, num: int) -> tuple[jax.Array, jax.Array, jax.Array]:
        """The rows [num] kept (distinct; a ranking rule: best first), their rollout mask [num] and the int32
        count of candidates the model turned down."""


def is_ranked(rule: Any) -> bool:
    """Whether a rule's rows are a ranking, best first (its class attribute `ranked`, True where it has none)."""
    return getattr(rule, "ranked", True)


def state_of(rule: Any, key: jax.Array, task: Any) -> Any:
    """A rule's state: its `init(key, task)`, or () for a rule without."""
    init = getattr(rule, "init", None)
    return () if init is None else init(key, task)


def updated_state(rule: Any, key: jax.Array, state: Any, proposal: Any, evaluated: Any) -> Any:
    """A rule's state after a generation: its `update(key, state, proposal, evaluated)`, or `state` without."""
    update = getattr(rule, "update", None)
    return state if update is None else update(key, state, proposal, evaluated)

