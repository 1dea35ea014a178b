"""Curiosity: a skill's record of children that opened niches reweighs the candidates varied from it.

Every rollout's insertion outcome is a label the run already has (`AddStatus.ADDED`: the child opened a niche).
`Curiosity` in a `ModelEmitter`'s chain counts, per repertoire slot, the children rolled out from it (`tried`)
and those that opened a niche (`opened`), from the first generation on. At its judge stage it multiplies each
candidate's parent novelty (`Judged.parent_novelty`, which `Diverse` reads as its parent factor with
`parent_weight` > 0) by

    ((O / r + prior) / (T + prior)) ** weight,   r = (sum of opened + 1/2) / (sum of tried + 1),

T and O the counts of the candidate's parent (with `near`, added over the skills in the parent's neighbour list
too: a parent's surroundings are a record even before it has children), r the run's rate of openers. Without a
record the factor is 1; with a long one it tends to (the parent's rate / the run's) ** weight: a skill whose
children keep opening niches is varied more, one whose children never do less, `prior` children's worth of
evidence being needed to move far from 1. A slot's record stays with the niche when its skill is replaced.
Candidates without a parent (-1) are left as they are, and so is a pool whose inner emitter names no parents.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core.checks import is_real
from mqd_jax.core.emitter import Evaluated, Proposal
from mqd_jax.core.repertoire import AddStatus, Repertoire
from mqd_jax.core.task import Task
from mqd_jax.emitters.acquisition import Judged
from mqd_jax.emitters.parts import Part, View


@dataclasses.dataclass(frozen=True)
class Curiosity(Part):
    """Reweighs candidates by their parents' record of opening niches (a part of a `ModelEmitter`'s chain; module
    doc). Its state: [2, C + 1] float32, per repertoire slot the children tried (row 0) and those that opened a
    niche (row 1); column C gathers the rows without a parent or not rolled out (outside every record and the rate).

    Attributes:
      weight: the exponent of the record's factor (0: no effect).
      prior: the children's worth of evidence at the run's rate that a record starts from.
      near: also count the records of the skills in the parent's neighbour list.
    """

    weight: float = 1.0
    prior: float = 4.0
    near: bool = True

    name = "curiosity"
    learns_in_warm_up = True  # every rollout is a label, warm-up's too
    sized = True  # its state holds a record per repertoire slot

    def __post_init__(self) -> None:
        if not (is_real(self.weight) and self.weight >= 0):
            raise ValueError(f"Curiosity.weight={self.weight!r} is invalid: expected a finite float >= 0")
        if not (is_real(self.prior) and self.prior > 0):
            raise ValueError(f"Curiosity.prior={self.prior!r} is invalid: expected a finite float > 0")
        if not isinstance(self.near, bool):
            raise ValueError(f"Curiosity.near={self.near!r} is invalid: expected a bool")

    def init(self, key: jax.Array, task: Task, capacity: int) -> jax.Array:
        return jnp.zeros((2, capacity + 1), jnp.float32)

    def factor(self, state: jax.Array, parents: jax.Array, repertoire: Repertoire) -> jax.Array:
        """[N] the record's factor of candidates whose parents' slots are `parents` [N] (-1: none, factor 1)."""
        records = state[:, :-1]  # [2, C]: tried, opened
        rate = (records[1].sum() + 0.5) / (records[0].sum() + 1.0)
        at = jnp.maximum(parents, 0)
        t, o = records[:, at]
        if self.near:
            listed = repertoire.neighbours.index[at]
            t, o = records[:, at] + jnp.where(listed >= 0, records[:, jnp.maximum(listed, 0)], 0.0).sum(axis=2)
        factor = ((o / rate + self.prior) / (t + self.prior)) ** self.weight
        return jnp.where(parents >= 0, factor, 1.0)

    def judged(self, state: jax.Array, judged: Judged, view: View) -> Judged:
        if judged.parents is None or judged.parent_novelty is None:
            return judged
        factor = self.factor(state, judged.parents, view.repertoire)
        return judged.replace(parent_novelty=judged.parent_novelty * factor)

    def update(self, state: jax.Array, info: Any, proposal: Proposal, evaluated: Evaluated) -> jax.Array:
        """The counts after a generation's rollouts (rows without a parent or not rolled out: column C)."""
        capacity = state.shape[1] - 1
        parents = proposal.info.parents
        if parents is None:
            return state
        at = jnp.where(proposal.rollout & (parents >= 0), parents, capacity)
        opened = (evaluated.status == AddStatus.ADDED).astype(jnp.float32)
        return state.at[0, at].add(1.0).at[1, at].add(opened)
