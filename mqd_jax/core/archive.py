"""The separate archive of skills the repertoire rejected or replaced.

The paper saves "all skills that are removed or not added to the repertoire" in
a separate archive. Here it is a ring buffer of fixed size A: it keeps the A
most recent such skills, and `total` counts every skill that ever went there,
so `min(total, A)` slots are filled and none is lost without being counted.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mqd_jax.core import pytree


@pytree.dataclass
class Archive:
    """Ring buffer of rejected and replaced skills.

    Attributes:
      actions: [A, n]; behaviors: [A, d]; qualities: [A].
      total: int32 scalar, skills ever archived; the newest is at (total - 1) % A.
    """

    actions: jax.Array
    behaviors: jax.Array
    qualities: jax.Array
    total: jax.Array

    @classmethod
    def empty(cls, size: int, action_dim: int, behavior_dim: int) -> Archive:
        return cls(
            actions=jnp.zeros((size, action_dim), jnp.float32),
            behaviors=jnp.zeros((size, behavior_dim), jnp.float32),
            qualities=jnp.zeros((size,), jnp.float32),
            total=jnp.int32(0),
        )

    @property
    def valid(self) -> jax.Array:
        """[A] which slots hold an archived skill."""
        return jnp.arange(self.qualities.shape[0]) < self.total


def push(archive: Archive, actions: jax.Array, behaviors: jax.Array, qualities: jax.Array,
         mask: jax.Array) -> Archive:
    """Appends the skills where mask[P] is set, in order, overwriting the oldest."""
    size = archive.qualities.shape[0]
    offset = jnp.cumsum(mask) - 1
    # When more than A skills arrive at once, only the last A are kept.
    keep = mask & (offset >= mask.sum() - size)
    slot = jnp.where(keep, (archive.total + offset) % size, size)
    return Archive(
        actions=archive.actions.at[slot].set(actions, mode="drop"),
        behaviors=archive.behaviors.at[slot].set(behaviors, mode="drop"),
        qualities=archive.qualities.at[slot].set(qualities, mode="drop"),
        total=archive.total + mask.sum(dtype=jnp.int32),
    )
