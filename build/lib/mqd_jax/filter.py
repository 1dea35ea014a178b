"""Algorithm 1's model-based filter: which candidates are worth a rollout.

From the model's predicted behavior b~ and quality q~ of a candidate, and the K
repertoire skills nearest to b~ in behavior space (paper, "Model-Based
Quality-Diversity Search"):

    predicted novelty             nov~ = mean_i ||b_nn_i - b~||
    predicted quality improvement qua~ = mean_i (q~ - q_nn_i)

A candidate is evaluated iff nov~ > t_nov or qua~ > t_qua (`passes`). With
fewer than K skills in the repertoire the means run over those there are; with
none, both scores are +inf (everything passes).

Budgeted filtering (`budgeted_order`) instead ranks an oversampled pool and
evaluates a fixed number of candidates from the top.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mqd_jax import neighbours
from mqd_jax.repertoire import Repertoire


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
    """[P] bool: Algorithm 1's test. NaN predictions fail it."""
    return (novelty > t_nov) | (improvement > t_qua)


def budgeted_order(novelty: jax.Array, improvement: jax.Array, t_nov: jax.Array) -> jax.Array:
    """[N] candidate indices, most promising first.

    First the candidates with nov~ > t_nov, by descending nov~; then the rest
    by descending qua~. Ties go to the higher qua~, then the lower index;
    NaN scores come last.
    """
    novel = novelty > t_nov
    primary = jnp.where(novel, novelty, improvement)
    # lexsort: the last key is the primary one; ascending, so negate; NaN sorts last.
    return jnp.lexsort((-improvement, -primary, ~novel)).astype(jnp.int32)
