"""Acquisition rules: which of a pool of candidates a model-based emitter rolls out.

From the model's predicted behavior b~ and quality q~ of a candidate, and the K
repertoire skills nearest to b~ in behavior space (paper, "Model-Based
Quality-Diversity Search"):

    predicted novelty             nov~ = mean_i ||b_nn_i - b~||
    predicted quality improvement qua~ = mean_i (q~ - q_nn_i)

With fewer than K skills in the repertoire the means run over those there are;
with none, both scores are +inf. A rule (`Threshold`: the paper's Algorithm 1;
`Budgeted`: a fixed number from the top of a ranked pool) is a frozen dataclass
with `pool_size(num)` (how many candidates it wants to choose `num` from) and
`select`, used by `mqd_jax.model_emitter.ModelEmitter`.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Protocol

import jax
import jax.numpy as jnp

from mqd_jax import neighbours
from mqd_jax.repertoire import Repertoire

if TYPE_CHECKING:
    from mqd_jax.config import Params


def predicted_scores(pred_behaviors: jax.Array, pred_qualities: jax.Array, rep: Repertoire,
                     k: int) -> tuple[jax.Array, jax.Array]:
    """nov~ [P] and qua~ [P] of predictions pred_behaviors [P, d], pred_qualities [P]."""
    d = jnp.where(rep.valid[None], neighbours.sq_dists(pred_behaviors, rep.behaviors), jnp.inf)
    sq, idx = neighbours.k_smallest(d, k)
    found = jnp.isfinite(sq)
    n = found.sum(1)
    mean = lambda x: jnp.where(n > 0, jnp.where(found, x, 0.0).sum(1) / jnp.maximum(n, 1), jnp.inf)  # noqa: E731
    novelty = mean(jnp.sqrt(jnp.where(found, sq, 0.0)))
    improvement = mean(pred_qualities[:, None] - rep.qualities[jnp.maximum(idx, 0)])
    return novelty, improvement


def passes(novelty: jax.Array, improvement: jax.Array, t_nov: jax.Array, t_qua: jax.Array) -> jax.Array:
    """[P] bool: Algorithm 1's test, nov~ > t_nov or qua~ > t_qua. NaN predictions fail it."""
    return (novelty > t_nov) | (improvement > t_qua)


def ranking(novelty: jax.Array, improvement: jax.Array, t_nov: jax.Array, wanted: jax.Array) -> jax.Array:
    """[N] candidate indices, most promising first.

    First the `wanted` [N] candidates (those the inner emitter would roll out),
    among them the ones with nov~ > t_nov by descending nov~, then the rest by
    descending qua~. Ties go to the higher qua~, then the lower index; NaN
    scores come last.
    """
    novel = novelty > t_nov
    primary = jnp.where(novel, novelty, improvement)
    # lexsort: the last key is the primary one; ascending, so negate; NaN sorts last.
    return jnp.lexsort((-improvement, -primary, ~novel, ~wanted)).astype(jnp.int32)


@dataclasses.dataclass(frozen=True)
class Threshold:
    """The paper's filter (Algorithm 1): of `num` candidates, roll out those that pass `params.t_nov` or
    `params.t_qua`; all of them during warm-up."""

    def pool_size(self, num: int) -> int:
        return num

    def select(self, novelty: jax.Array, improvement: jax.Array, wanted: jax.Array, warm_up: jax.Array,
               params: Params, num: int) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Rows [num] of the pool kept, their rollout mask [num] and how many wanted candidates were turned down."""
        rollout = wanted & (warm_up | passes(novelty, improvement, params.t_nov, params.t_qua))
        return jnp.arange(num), rollout, (wanted & ~rollout).sum(dtype=jnp.int32)


@dataclasses.dataclass(frozen=True)
class Budgeted:
    """Budgeted ranking: rank `pool_factor` x num candidates (`ranking`) and roll out the top num; during
    warm-up the pool's first num candidates."""

    pool_factor: int = 4

    def __post_init__(self) -> None:
        if not (isinstance(self.pool_factor, int) and self.pool_factor >= 1):
            raise ValueError(f"Budgeted.pool_factor={self.pool_factor!r} is invalid: expected an int >= 1")

    def pool_size(self, num: int) -> int:
        return num * self.pool_factor

    def select(self, novelty: jax.Array, improvement: jax.Array, wanted: jax.Array, warm_up: jax.Array,
               params: Params, num: int) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Rows [num] of the pool kept, their rollout mask [num] and how many candidates were turned down."""
        top = jnp.where(warm_up, jnp.arange(num), ranking(novelty, improvement, params.t_nov, wanted)[:num])
        discarded = jnp.where(warm_up, 0, novelty.shape[0] - num).astype(jnp.int32)
        return top, wanted[top], discarded


class Acquisition(Protocol):
    """What `ModelEmitter` needs of a rule (`Threshold` and `Budgeted` are two; a user's own is a third)."""

    def pool_size(self, num: int) -> int:
        """How many candidates the rule chooses `num` from."""

    def select(self, novelty: jax.Array, improvement: jax.Array, wanted: jax.Array, warm_up: jax.Array,
               params: Params, num: int) -> tuple[jax.Array, jax.Array, jax.Array]:
        """From the pool's scores [N] and the inner emitter's rollout mask `wanted` [N]: the rows [num] kept, their
        rollout mask [num] and the int32 count of candidates the model turned down."""
