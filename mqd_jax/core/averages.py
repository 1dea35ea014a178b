"""Exponential running averages that wait for their first value (a pursuit's success rates, anchoring's errors)."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def running_average(average: jax.Array, value: jax.Array, weight: float, seen: jax.Array) -> jax.Array:
    """An exponential average after one more value: (1 - weight) * average + weight * value where `seen`;
    the value itself where the average is still NaN (none yet); the average unchanged where not `seen`."""
    updated = jnp.where(jnp.isnan(average), value, (1 - weight) * average + weight * value)
    return jnp.where(seen, updated, average)
