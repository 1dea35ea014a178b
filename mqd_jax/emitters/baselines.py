"""The paper's baseline emitters: `Uniform` (RANDOM) and `IsoLine` (QD) (the protocol: `mqd_jax.core.emitter`)."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import pytree, selection, variation
from mqd_jax.core.checks import check_traced, is_real
from mqd_jax.core.emitter import Emitter, Proposal, action_bounds
from mqd_jax.core.params import Params
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.task import Task


def _uniform_key(key: jax.Array) -> jax.Array:
    # The first of IsoLine's three subkeys: RANDOM's candidates equal QD's first generation for the same key.
    return jax.random.split(key, 3)[0]


@dataclasses.dataclass(frozen=True)
class Uniform(Emitter):
    """RANDOM: actions uniform in the task's action box, all rolled out."""

    def propose(self, key: jax.Array, state: Any, repertoire: Repertoire, task: Task, params: Params,
                num: int) -> Proposal:
        return Proposal(variation.uniform(_uniform_key(key), num, *action_bounds(task)), jnp.ones(num, bool),
                        parents=jnp.full(num, -1, jnp.int32))


@pytree.dataclass
class IsoLineParams:
    """IsoLine's traced parameters: the iso step `iso_sigma` (x the action range) and the line step `line_sigma`."""

    iso_sigma: jax.Array
    line_sigma: jax.Array


@dataclasses.dataclass(frozen=True)
class IsoLine(Emitter):
    """QD: parents drawn in proportion to novelty, iso+line children (Vassiliades & Mouret 2018):
    `x1 + iso_sigma (high - low) N(0, I) + line_sigma (x2 - x1) N(0, 1)`.

    Uniform actions while the repertoire is empty; every candidate is rolled out. A child's `parents` entry is
    its first parent x1, from which the iso noise starts (-1 for a uniform action).

    `scales` (finite floats > 0): the children come in equal parts (the first parts one larger where `num` does
    not divide), part i with both steps times `scales[i]`, each part from its own key `fold_in(key, i)`. One
    scale (the default, (1.0,), the paper's QD) draws from `key` itself.

    `iso_sigma`, `line_sigma` (finite floats >= 0): the defaults of its traced parameters (`IsoLineParams`).
    """

    scales: tuple[float, ...] = (1.0,)
    iso_sigma: float = 0.02
    line_sigma: float = 0.1

    def __post_init__(self) -> None:
        if not (isinstance(self.scales, tuple) and self.scales and all(is_real(s) and s > 0 for s in self.scales)):
            raise ValueError(f"IsoLine.scales={self.scales!r} is invalid: expected a non-empty tuple of finite "
                             "floats > 0")
        for name in ("iso_sigma", "line_sigma"):
            if not (is_real(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"IsoLine.{name}={getattr(self, name)!r} is invalid: expected a finite float >= 0")

    def default_params(self) -> IsoLineParams:
        return IsoLineParams(jnp.float32(self.iso_sigma), jnp.float32(self.line_sigma))

    def check_params(self, params: IsoLineParams) -> None:
        for name in ("iso_sigma", "line_sigma"):
            check_traced("IsoLine.params", name, getattr(params, name))

    def propose(self, key: jax.Array, state: Any, repertoire: Repertoire, task: Task, params: Params,
                num: int) -> Proposal:
        if len(self.scales) == 1:
            return self._children(key, repertoire, task, params, self.scales[0], num)
        sizes = [num // len(self.scales) + (i < num % len(self.scales)) for i in range(len(self.scales))]
        parts = [self._children(jax.random.fold_in(key, i), repertoire, task, params, scale, size)
                 for i, (scale, size) in enumerate(zip(self.scales, sizes, strict=True))]
        return jax.tree.map(lambda *rows: jnp.concatenate(rows), *parts)

    @staticmethod
    def _children(key: jax.Array, repertoire: Repertoire, task: Task, params: Params, scale: float,
                  num: int) -> Proposal:
        """`num` children with both steps times `scale`."""
        low, high = action_bounds(task)
        _, k_parents, k_vary = jax.random.split(key, 3)
        fresh = variation.uniform(_uniform_key(key), num, low, high)
        parents = selection.sample_parents(k_parents, repertoire.novelty, repertoire.valid, 2 * num)
        x = repertoire.actions[parents].reshape(2, num, -1)
        children = variation.iso_line(k_vary, x[0], x[1], params.emitter.iso_sigma * scale,
                                      params.emitter.line_sigma * scale, low, high)
        bred = repertoire.count > 0
        return Proposal(jnp.where(bred, children, fresh), jnp.ones(num, bool),
                        parents=jnp.where(bred, parents[:num], -1).astype(jnp.int32))
