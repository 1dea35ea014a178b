"""Parent selection: sampled from the repertoire proportionally to novelty."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def probabilities(novelty: jax.Array, valid: jax.Array) -> jax.Array:
    """[C] selection probability of each skill: novelty / total novelty.

    If every valid skill has zero novelty (e.g. a single skill), all valid
    skills are equally likely.
    """
    w = jnp.where(valid, novelty, 0.0)
    w = jnp.where(w.sum() > 0, w, valid.astype(w.dtype))
    return w / jnp.maximum(w.sum(), 1e-30)


def sample_parents(key: jax.Array, novelty: jax.Array, valid: jax.Array, num: int) -> jax.Array:
    """[num] slots drawn with replacement, proportionally to `probabilities`.

    Inverse-CDF sampling: O(C + num log C), unlike a categorical over [num, C].
    """
    cdf = jnp.cumsum(probabilities(novelty, valid))
    u = jax.random.uniform(key, (num,), maxval=cdf[-1])
    idx = jnp.searchsorted(cdf, u, side="right")
    return jnp.minimum(idx, novelty.shape[0] - 1).astype(jnp.int32)
