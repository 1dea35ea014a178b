"""Candidate generation: uniform sampling and iso+line variation."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def uniform(key: jax.Array, num: int, low: jax.Array, high: jax.Array) -> jax.Array:
    """[num, n] actions uniform in the box [low, high]."""
    return jax.random.uniform(key, (num, low.shape[0]), minval=low, maxval=high)


def iso_line(key: jax.Array, x1: jax.Array, x2: jax.Array, iso_sigma: jax.Array, line_sigma: jax.Array,
             low: jax.Array, high: jax.Array) -> jax.Array:
    """Iso+line operator (Vassiliades & Mouret, GECCO 2018) on parents x1, x2: [P, n].

    child = x1 + iso_sigma * (high - low) * N(0, I) + line_sigma * (x2 - x1) * N(0, 1),
    i.e. a Gaussian mutation scaled to the action range plus a crossover step
    along the line through both parents; clipped to the action bounds.
    """
    k_iso, k_line = jax.random.split(key)
    iso = iso_sigma * (high - low) * jax.random.normal(k_iso, x1.shape)
    line = line_sigma * (x2 - x1) * jax.random.normal(k_line, (x1.shape[0], 1))
    return jnp.clip(x1 + iso + line, low, high)
