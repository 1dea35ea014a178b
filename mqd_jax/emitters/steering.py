"""Steering: children aimed at empty behavior space by the model's Jacobian (one step of the paper's skill
adaptation, without its rollout).

A `ModelEmitter` with `Steering()` in its chain of parts replaces the last `share` of its
inner emitter's pool with steered children before the acquisition rule ranks
the pool (off during warm-up and while the repertoire is empty; a child whose Jacobian is not finite is not
steered: its row keeps the inner candidate). The inner emitter's `update` then sees its proposal with those
rows' actions replaced (IsoLine and Uniform keep no per-candidate state). Each steered child comes from a
target drawn uniformly in the behavior box and the skill whose behavior is nearest to it (so a skill is
drawn in proportion to its Voronoi cell, which is largest at the repertoire's
frontier: the bias of a rapidly-exploring random tree, LaValle 1998). The
child is one step of the model's pseudo-inverse Jacobian from that skill,
toward the target, for a behavior step of U(`step_low`, `step_high`) x
t_dist (the whole way when the target is nearer):

    a' = clip(a_j + pinv(J(a_j)) min(s, ||b* - b_j||) (b* - b_j) / ||b* - b_j||).

With `parents="novelty"` the skill is drawn as IsoLine draws its parents (in
proportion to novelty, also frontier-biased) and the step takes a direction
uniform on the sphere. `step="mutation"` replaces the model's step by an iso
mutation of the drawn skill: the same parents without the model (an ablation).

With `quality` > 0 the child also climbs the model's predicted quality
without moving its linearized behavior: the quality gradient g projected on
the Jacobian's null space, (I - pinv(J) J) g, scaled to `quality` x the
length of the behavior step's action change, is added to that change.

Where behavior is smooth in the action (the planar arm, 2D Obstacle away
from walls) the child lands near its aim, at a new niche's distance from
its parent; where contact makes it rugged (2D Object) the step is as blind
as a mutation, and the acquisition rule and the fallback judge it like any
other candidate.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import repertoire as repertoire_lib
from mqd_jax.core import selection
from mqd_jax.core.checks import is_real
from mqd_jax.core.emitter import Evaluated, Proposal, action_bounds
from mqd_jax.core.params import Params
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.task import Task
from mqd_jax.emitters.parts import Part, View, is_share

# actions [m, n] -> the model's behavior Jacobians [m, d, n] (real units) at them.
Jacobian = Callable[[jax.Array], jax.Array]
PARENTS = ("voronoi", "novelty")
STEPS = ("jacobian", "mutation")


@dataclasses.dataclass(frozen=True)
class Steering(Part):
    """How many of a pool's candidates are steered, and how far (a part of a `ModelEmitter`'s chain; module doc).

    Metrics: `steered` (the generation's rollouts that were steered children) and, with a pursuit,
    `steering_share` (its share of the steerable rows this generation).

    Attributes:
      share: the fraction of the pool replaced by steered children (its last rows), in (0, 1).
      step_low, step_high: the behavior step, uniform in [step_low, step_high] x t_dist (0 < low <= high).
      parents: "voronoi" (the skill nearest to a target uniform in the behavior box, toward it) or "novelty"
        (drawn as IsoLine draws parents, in proportion to novelty, toward a direction uniform on the sphere).
      step: "jacobian" (the model's step toward the aim) or "mutation" (the ablation without the model: the
        parent's iso mutation, `iso_sigma` x the action range, as IsoLine's without its line term).
      iso_sigma: the step="mutation" ablation's iso step (IsoLine's default).
      quality: the null-space step up the model's quality gradient, as a multiple of the behavior step's
        action length (0: none; needs step="jacobian").
      pursuit: None to steer `share` of the pool at every generation, or a share (`parts.Share`: a
        `pursuit.Fallback`, whose share, from 1/2 within [floor, 1 - floor], pursues whichever of steered and
        other rollouts has recently opened new niches more often) of those rows to steer.
    """

    share: float = 0.5
    step_low: float = 1.0
    step_high: float = 3.0
    parents: str = "voronoi"
    pursuit: Any = None
    step: str = "jacobian"
    quality: float = 0.0
    iso_sigma: float = 0.02

    name = "steering"
    needs_ranking = "Threshold would roll out every steered child"

    def __post_init__(self) -> None:
        for name in ("share", "step_low", "step_high"):
            value = getattr(self, name)
            if not (is_real(value) and value > 0):
                raise ValueError(f"Steering.{name}={value!r} is invalid: expected a finite float > 0")
        if self.share >= 1:
            raise ValueError(f"Steering.share={self.share!r} is invalid: expected a float in (0, 1) (the inner "
                             "emitter keeps the rest of the pool)")
        if self.parents not in PARENTS:
            raise ValueError(f"Steering.parents={self.parents!r} is invalid: expected one of {PARENTS}")
        if self.step not in STEPS:
            raise ValueError(f"Steering.step={self.step!r} is invalid: expected one of {STEPS}")
        if self.pursuit is not None and not is_share(self.pursuit):
            raise ValueError(f"Steering.pursuit={self.pursuit!r} is invalid: expected None or a share "
                             "(mqd_jax.emitters.parts.Share, such as Fallback())")
        for name in ("quality", "iso_sigma"):
            if not (is_real(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"Steering.{name}={getattr(self, name)!r} is invalid: expected a finite float >= 0")
        if self.quality and self.step != "jacobian":
            raise ValueError(f"Steering.quality={self.quality!r} needs step='jacobian' (the model's quality gradient)")
        if self.step_low > self.step_high:
            raise ValueError(f"Steering: step_low={self.step_low!r} > step_high={self.step_high!r}")

    def count(self, pool_size: int) -> int:
        """The most rows steered in a pool of `pool_size`."""
        return round(self.share * pool_size)

    def check_run(self, pool_size: int, num: int) -> None:
        """ValueError unless at least 1 row of a pool of `pool_size` is steered, leaving `num` to the inner
        emitter."""
        count = self.count(pool_size)
        if not 1 <= count <= pool_size - num:
            raise ValueError(f"ModelEmitter: {self!r} steers {count} of a pool of {pool_size}: expected at least 1, "
                             f"leaving the inner emitter at least the {num} rollouts of a generation (a smaller "
                             "share, or a larger pool)")

    def init(self, key: jax.Array, task: Task) -> Any:
        return () if self.pursuit is None else self.pursuit.init(key, task)

    def metrics(self) -> dict[str, Any]:
        return {"steered": jnp.int32, **({} if self.pursuit is None else {"steering_share": jnp.float32})}

    def pool(self, key: jax.Array, state: Any, pool: Proposal, view: View) -> tuple[Proposal, jax.Array]:
        """The pool [P] with its last rows replaced by steered children (not during warm-up or while the
        repertoire is empty; their `parents` by the steering parents where the pool names parents), and which
        rows [P] were."""
        pool_size, task, model = pool.actions.shape[0], view.task, view.model
        count = self.count(pool_size)
        self.check_run(pool_size, view.num)
        # Reverse mode where the behavior has fewer dimensions than the action (d VJPs rather than n JVPs: 4x
        # faster through PushCube's IK). Reverse mode turns a masked branch's NaN (a norm's gradient at 0 under a
        # `where`) into a NaN Jacobian where forward mode does not: a child that is not finite is not steered, its
        # row keeps the inner emitter's candidate.
        differentiate = jax.jacrev if task.behavior_dim < task.action_dim else jax.jacfwd
        jacobian = jax.vmap(differentiate(lambda a: model.predict(view.surrogate, a, task)[0]))
        quality_gradient = jax.vmap(jax.grad(lambda a: model.predict(view.surrogate, a, task)[1]))
        children, steering_parents = self.steer(jax.random.fold_in(key, 2), view.repertoire, jacobian, task,
                                                view.params, count, quality_gradient)
        on = ~view.warm_up & (view.repertoire.count > 0)
        steered_rows = count if self.pursuit is None else jnp.round(self.pursuit.share(state) * count)
        finite = jnp.zeros(pool_size, bool).at[pool_size - count:].set(jnp.isfinite(children).all(axis=1))
        steered = on & finite & (jnp.arange(pool_size) >= pool_size - steered_rows)

        def spliced(rows: jax.Array, steered_values: jax.Array) -> jax.Array:
            """rows [P, ...] with the steered ones among the last `count` taken from steered_values [count, ...]."""
            on_tail = steered[pool_size - count:].reshape((count,) + (1,) * (rows.ndim - 1))
            return rows.at[pool_size - count:].set(jnp.where(on_tail, steered_values, rows[pool_size - count:]))

        parents = None if pool.parents is None else spliced(pool.parents, steering_parents)
        return pool.replace(actions=spliced(pool.actions, children), parents=parents), steered

    def update(self, state: Any, info: tuple[jax.Array, Any], proposal: Proposal, evaluated: Evaluated) -> Any:
        """The pursuit's state after a generation whose kept rows info[0] [P] were steered."""
        if self.pursuit is None:
            return state
        return self.pursuit.learn(state, info[0] & proposal.rollout, proposal.info.predicted_behaviors, evaluated)

    def report(self, state: Any, info: tuple[jax.Array, Any], proposal: Proposal,
               evaluated: Evaluated) -> dict[str, jax.Array]:
        steered = {"steered": (info[0] & proposal.rollout).sum(dtype=jnp.int32)}
        return steered if self.pursuit is None else {**steered, "steering_share": self.pursuit.share(state)}

    def steer(self, key: jax.Array, repertoire: Repertoire, jacobian: Jacobian, task: Task, params: Params,
              num: int, quality_gradient: Jacobian | None = None) -> tuple[jax.Array, jax.Array]:
        """[num, n] steered children of a non-empty repertoire (see the module's doc) and their parents' slots
        [num] int32; `quality_gradient` (actions [m, n] -> the model's quality gradients [m, n]) is needed with
        `quality` > 0."""
        low, high = action_bounds(task)
        if self.step == "mutation":
            k_target, k_step, k_iso = jax.random.split(key, 3)
            parents, _ = self.aims(k_target, k_step, repertoire, task, params, num)
            change = self.iso_sigma * (high - low) * jax.random.normal(k_iso, (num, low.shape[0]))
            return jnp.clip(repertoire.actions[parents] + change, low, high), parents
        k_target, k_step = jax.random.split(key)
        parents, aim = self.aims(k_target, k_step, repertoire, task, params, num)
        actions = repertoire.actions[parents]
        gradients = quality_gradient(actions) if self.quality else None
        return jacobian_step(actions, jacobian(actions), aim, task, gradients, self.quality), parents

    def aims(self, k_target: jax.Array, k_step: jax.Array, repertoire: Repertoire, task: Task, params: Params,
             num: int) -> tuple[jax.Array, jax.Array]:
        """The steered children's parents (slots [num] int32) and the behavior changes [num, d] they are aimed
        at."""
        if self.parents == "voronoi":
            behavior_low = jnp.asarray(task.behavior_low, jnp.float32)
            behavior_high = jnp.asarray(task.behavior_high, jnp.float32)
            targets = jax.random.uniform(k_target, (num, task.behavior_dim), minval=behavior_low,
                                         maxval=behavior_high)
            parents = jnp.maximum(repertoire_lib.k_nearest(repertoire, targets, 1)[1][:, 0], 0)
            offset = targets - repertoire.behaviors[parents]
        else:  # a direction uniform on the sphere, from a target infinitely far
            k_parents, k_direction = jax.random.split(k_target)
            parents = selection.sample_parents(k_parents, repertoire.novelty, repertoire.valid, num)
            offset = jax.random.normal(k_direction, (num, task.behavior_dim)) * 1e6
        distance = jnp.linalg.norm(offset, axis=1, keepdims=True)
        step = params.t_dist * jax.random.uniform(k_step, (num, 1), minval=self.step_low, maxval=self.step_high)
        return parents, offset * jnp.minimum(1.0, step / jnp.maximum(distance, 1e-12))


def jacobian_step(actions: jax.Array, jacobians: jax.Array, aim: jax.Array, task: Task,
                  gradients: jax.Array | None = None, quality: float = 0.0) -> jax.Array:
    """Actions [m, n] moved by pinv(J) aim (Jacobians [m, d, n], aimed behavior changes [m, d]), clipped to the
    task's action box: the least-norm change that makes the linearized behavior move by the aim. With quality
    gradients [m, n] and `quality` > 0, plus their null-space part (I - pinv(J) J) g at `quality` x that change's
    length, which the linearized behavior does not see."""
    inverse = jnp.linalg.pinv(jacobians)
    change = jnp.einsum("mnd,md->mn", inverse, aim)
    if quality:
        null = gradients - jnp.einsum("mnd,md->mn", inverse, jnp.einsum("mdn,mn->md", jacobians, gradients))
        length = quality * jnp.linalg.norm(change, axis=1, keepdims=True)
        change = change + length * null / jnp.maximum(jnp.linalg.norm(null, axis=1, keepdims=True), 1e-12)
    return jnp.clip(actions + change, *action_bounds(task))
