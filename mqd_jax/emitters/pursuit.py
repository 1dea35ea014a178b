"""Adaptive pursuit (Thierens 2005) between two sources of rollouts: how far a model emitter trusts its model
(`Fallback` in its chain), and how much of its pool it steers (`steering.Steering.pursuit`)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from mqd_jax.core import pytree
from mqd_jax.core.averages import running_average
from mqd_jax.core.checks import is_real
from mqd_jax.core.emitter import Evaluated
from mqd_jax.core.repertoire import AddStatus
from mqd_jax.core.task import Task
from mqd_jax.emitters.parts import Share


@pytree.dataclass
class FallbackState:
    """Adaptive pursuit's state.

    Attributes:
      share: float32, the first side's share of the next generation (a fallback: the model's choice's share
        of the rollouts; steering: the share of its rows steered).
      success: [2] float32, exponential averages of the fraction of rollouts that
        opened a niche: the first side's, the other's (NaN before the first).
    """

    share: jax.Array
    success: jax.Array


@dataclasses.dataclass(frozen=True)
class Fallback(Share):
    """How far a `ModelEmitter` trusts its model: adaptive pursuit (Thierens 2005) between the model's choice
    and the inner emitter's own candidates (a part of its chain: the rule's first round(share x num) rows, the
    rest the inner emitter's own first candidates), or between steered children and the rest (`Steering.pursuit`).

    After each generation past warm-up, each side's success (the fraction of
    its rollouts that opened a niche, `AddStatus.ADDED`: what coverage counts) enters an exponential average
    with weight `rate`; the model's share then moves by `rate` toward
    1 - `floor` if its average is the higher, else toward `floor`. The share
    starts at 1/2.
    """

    floor: float = 0.1
    rate: float = 0.2

    name = "fallback"
    needs_ranking = "it keeps the rule's first rows"

    def __post_init__(self) -> None:
        for name, low, high in (("floor", 0.0, 0.5), ("rate", 0.0, 1.0)):
            value = getattr(self, name)
            if not (is_real(value) and low <= value <= high):
                raise ValueError(f"Fallback.{name}={value!r} is invalid: expected a float in [{low}, {high}]")

    def init(self, key: jax.Array | None = None, task: Task | None = None) -> FallbackState:
        return FallbackState(share=jnp.float32(0.5), success=jnp.full(2, jnp.nan, jnp.float32))

    def share(self, state: FallbackState) -> jax.Array:
        return state.share

    def learn(self, state: FallbackState, first: jax.Array, predicted: jax.Array,
              evaluated: Evaluated) -> FallbackState:
        """The state after a generation whose rows [P] `first` came from the first side (the model's choice;
        steered children)."""
        success = evaluated.status == AddStatus.ADDED
        rolled = evaluated.status != AddStatus.SKIPPED
        sides = jnp.stack([first, ~first]) & rolled
        count = sides.sum(axis=1)
        rate = (sides & success).sum(axis=1) / jnp.maximum(count, 1)
        averaged = running_average(state.success, rate, self.rate, count > 0)
        target = jnp.where(averaged[0] > averaged[1], 1.0 - self.floor, self.floor)
        share = jnp.where(jnp.isnan(averaged).any(), state.share, state.share + self.rate * (target - state.share))
        return FallbackState(share=share.astype(jnp.float32), success=averaged.astype(jnp.float32))
