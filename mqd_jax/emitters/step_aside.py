"""Stepping aside: a model emitter hands its generation to the inner emitter while its model predicts the
rollouts no better than chance."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import pytree
from mqd_jax.core.averages import running_average
from mqd_jax.core.checks import is_real
from mqd_jax.core.emitter import Evaluated
from mqd_jax.core.task import Task
from mqd_jax.emitters.parts import Share


def explained(predicted: jax.Array, evaluated: Evaluated) -> jax.Array:
    """The share of the variance of the usable rollouts' behaviors [P, d] that predictions [P, d] explain:
    1 - sum ||b - b~||^2 / sum ||b - mean b||^2 over the usable rows (R^2; 0: no better than predicting their
    mean, below 0: worse). NaN with fewer than two usable rows or behaviors all equal."""
    usable = evaluated.usable[:, None]
    n = evaluated.usable.sum()
    mean = jnp.where(usable, evaluated.behaviors, 0.0).sum(0) / jnp.maximum(n, 1)
    spread = jnp.where(usable, (evaluated.behaviors - mean) ** 2, 0.0).sum()
    error = jnp.where(usable, (evaluated.behaviors - predicted) ** 2, 0.0).sum()
    return jnp.where((n >= 2) & (spread > 0), 1.0 - error / jnp.where(spread > 0, spread, 1.0), jnp.nan)


@pytree.dataclass
class StepAsideState:
    """Attributes:
      skill: float32, the exponential average of the generations' explained variance (NaN before the first).
    """

    skill: jax.Array


@dataclasses.dataclass(frozen=True)
class StepAside(Share):
    """The model's measured skill decides whether it chooses at all (a part of a `ModelEmitter`'s chain; its share
    is 1 or 0). Metric: `model_skill` (the averaged explained variance the generation was chosen with; NaN
    before one).

    After each generation past warm-up, the share of the variance of its usable rollouts' behaviors that the
    model's predictions explained (`explained`, measured before the model trains on them: 1 is exact, 0 is no
    better than predicting their mean) enters an exponential average with weight `rate`. While that average is
    below `margin`, the model's share of the next generation is 0: the generation rolls out the inner emitter's
    first candidates as the inner emitter proposed them (IsoLine: plain QD emission; steered rows come last in
    the pool, so none are rolled out). The model still predicts every row, so its skill is still measured, and
    a model that learns comes back. A generation with fewer than two usable rollouts leaves the average as it
    was.
    """

    margin: float = 0.1
    rate: float = 0.2

    name = "step_aside"
    needs_ranking = "it hands the generation to the inner emitter's first rows"

    def __post_init__(self) -> None:
        for name, low, high in (("margin", -1.0, 1.0), ("rate", 0.0, 1.0)):
            value = getattr(self, name)
            if not (is_real(value) and low <= value <= high):
                raise ValueError(f"StepAside.{name}={value!r} is invalid: expected a float in [{low}, {high}]")

    def init(self, key: jax.Array | None = None, task: Task | None = None) -> StepAsideState:
        return StepAsideState(skill=jnp.float32(jnp.nan))

    def metrics(self) -> dict[str, Any]:
        return {"model_skill": jnp.float32}

    def share(self, state: StepAsideState) -> jax.Array:
        """1 while the model is trusted (`trusts`), else 0."""
        return jnp.where(self.trusts(state), 1.0, 0.0).astype(jnp.float32)

    def learn(self, state: StepAsideState, first: jax.Array, predicted: jax.Array,
              evaluated: Evaluated) -> StepAsideState:
        """The state after a generation whose predictions [P, d] explained some of its behaviors (`explained`)."""
        return self.averaged(state, explained(predicted, evaluated))

    def averaged(self, state: StepAsideState, skill: jax.Array) -> StepAsideState:
        """The state after a generation whose predictions explained `skill` of its behaviors (NaN: not measured)."""
        seen = ~jnp.isnan(skill)
        return StepAsideState(running_average(state.skill, jnp.where(seen, skill, 0.0), self.rate, seen)
                              .astype(jnp.float32))

    def report(self, state: StepAsideState, info: Any, proposal: Any, evaluated: Evaluated) -> dict[str, jax.Array]:
        return {"model_skill": state.skill}

    def trusts(self, state: StepAsideState) -> jax.Array:
        """bool: the model chooses (its averaged skill is not below `margin`; True before any is measured)."""
        return ~(state.skill < self.margin)
