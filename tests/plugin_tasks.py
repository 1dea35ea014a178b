"""Tasks a user's own package might hold, loaded by name ("plugin_tasks:make_reach") or entry point."""

import dataclasses

import jax.numpy as jnp

from mqd_jax import Task


@dataclasses.dataclass(frozen=True, eq=False)
class Reach(Task):
    """A 2-link planar arm: behavior = end-effector position, quality = -joint effort / scale.

    `scale` 1 keeps qualities inside `quality_range`; a smaller scale pushes them out of it.
    """

    quality_range = (-6.3, 0.0)
    scale: float = 1.0
    offset: float = 0.0  # moves behaviors: a non-zero offset puts some outside the behavior box
    valid: bool = True

    def evaluate(self, actions, key):
        a1, a2 = actions[:, 0], actions[:, 0] + actions[:, 1]
        tip = 0.5 + self.offset + 0.25 * jnp.stack([jnp.cos(a1) + jnp.cos(a2), jnp.sin(a1) + jnp.sin(a2)], axis=1)
        return tip, -jnp.abs(actions).sum(1) / self.scale, jnp.full(actions.shape[0], self.valid)


def make_reach(**changes) -> Reach:
    return Reach((-3.14, -3.14), (3.14, 3.14), (0.0, 0.0), (1.0, 1.0), **changes)


@dataclasses.dataclass(frozen=True, eq=False)
class Waves(Task):
    """Behaviors in d dimensions: behavior_j = (1 + sin(a_j + a_{j+1} / 2)) / 2 in [0, 1]^d for actions of d + 1
    numbers in [-2, 2]; quality = -mean(a^2) / 4."""

    quality_range = (-1.0, 0.0)

    def evaluate(self, actions, key):
        d = self.behavior_dim
        behaviors = (1 + jnp.sin(actions[:, :d] + actions[:, 1:d + 1] / 2)) / 2
        return behaviors, -(actions**2).mean(1) / 4, jnp.ones(actions.shape[0], bool)


def make_waves(dims: int = 3) -> Waves:
    return Waves((-2.0,) * (dims + 1), (2.0,) * (dims + 1), (0.0,) * dims, (1.0,) * dims)
