"""QD run inside the model: only what the imagined generations add is rolled out.

`Imagination(inner, generations=G)` is a `ModelEmitter` whose proposal comes
from G imagined generations (the idea of Dynamics-Aware QD, Lim, Grillotti and
Cully 2022): each asks `inner` for `num` candidates from the imagined
repertoire, predicts their outcomes with the model (anchored as `anchoring`
says) and inserts them with the paper's rule, so later imagined generations
breed from imagined skills. The candidates still in the imagined repertoire at
the end (added or improving, and not displaced by a later imagined one) are
worth a rollout; the first `num` of them, earliest generation first, are
proposed and rolled out, and the generation's other rows are skipped (they
count as `discarded`). During warm-up the first imagined generation's
candidates are rolled out as `inner` proposed them. Training, metrics and
anchoring are the `ModelEmitter`'s; its `acquisition` is not used, and a
`fallback` is refused (the rows are not a ranking it could share).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import repertoire as repertoire_lib
from mqd_jax.core.checks import is_int
from mqd_jax.core.emitter import Proposal
from mqd_jax.core.params import Params
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.task import Task
from mqd_jax.emitters.model_emitter import ModelEmitter, ModelEmitterState


def survivors(written: jax.Array, capacity: int) -> jax.Array:
    """written [G, P]: the slot each imagined candidate's skill ended its generation in (`capacity` if none) ->
    [G, P] bool, still there after the last generation (no later generation wrote its slot)."""
    g = written.shape[0]
    flat = written.reshape(-1)
    later = jnp.repeat(jnp.arange(g), written.shape[1])
    overwritten = ((flat[:, None] == flat[None, :]) & (later[None, :] > later[:, None])).any(axis=1)
    return ((flat < capacity) & ~overwritten).reshape(written.shape)


@dataclasses.dataclass(frozen=True)
class Imagination(ModelEmitter):
    """A `ModelEmitter` that rolls out what `generations` imagined generations of `inner` add (module doc).

    Attributes (beyond `ModelEmitter`'s):
      generations: the imagined generations per real one.
    """

    generations: int = 3

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (is_int(self.generations) and self.generations >= 1):
            raise ValueError(f"Imagination.generations={self.generations!r} is invalid: expected an int >= 1")
        if self.fallback is not None:
            raise ValueError(f"Imagination.fallback={self.fallback!r} is invalid: expected None (the imagined "
                             "rows are not a ranking a Fallback could share)")
        if self.steering is not None:
            raise ValueError(f"Imagination.steering={self.steering!r} is invalid: expected None (imagined "
                             "generations draw their own pools)")
        if self.model.validity is not None:
            raise ValueError(f"Imagination.surrogate.validity={self.model.validity!r} is invalid: expected None "
                             "(no acquisition rule reads it: what the imagined generations add is rolled out)")

    def propose(self, key: jax.Array, state: ModelEmitterState, repertoire: Repertoire, task: Task, params: Params,
                num: int) -> Proposal:
        def imagine(rep: Repertoire, key: jax.Array) -> tuple[Repertoire, tuple[Any, ...]]:
            pool = self.inner.propose(key, state.inner, rep, task, params.part(params.emitter.inner), num)
            x = self.model.inputs(pool.actions, task)
            features = x[:, task.action_dim:] if self.keeps_features(task) else x[:, :0]  # [num, 0]: none kept
            plain, anchored = self.predictions(state, pool.actions, rep, task, pool.parents, x)
            predicted = self.chosen(state, plain, anchored).mean(axis=0)
            rep, ins = repertoire_lib.insert(rep, pool.actions, predicted[:, :-1], predicted[:, -1], pool.rollout,
                                             params.t_dist, self.k, repertoire_lib.NUM_NEAR, chunk=32,
                                             features=features)
            # anchoring "auto" compares both predictions on the rollouts (ModelEmitter.update).
            both = (plain.mean(axis=0), anchored.mean(axis=0)) if self.anchoring == "auto" else ()
            return rep, (pool, predicted, both, repertoire_lib.written_slots(ins, rep.capacity), features)

        _, (pools, predicted, both, written, features) = jax.lax.scan(
            imagine, repertoire, jax.random.split(key, self.generations))
        kept = survivors(written, repertoire.capacity).reshape(-1)
        warm_up = state.evaluations < self.warmup_samples
        rows = jnp.where(warm_up, jnp.arange(num), jnp.argsort(~kept, stable=True)[:num])
        flat = lambda x: x.reshape(-1, *x.shape[2:])[rows]  # noqa: E731  [G, num, ...] -> the kept rows [num, ...]
        wanted = flat(pools.rollout)
        rollout = jnp.where(warm_up, wanted, wanted & kept[rows])
        # The predicted distance to the nearest real skill: the opener AUC's score.
        behaviors = flat(predicted)[:, :-1]
        sq, _ = repertoire_lib.nearest(repertoire, repertoire.behaviors, behaviors)
        info = {"inner": jax.tree.map(flat, pools.info), "predicted_behaviors": behaviors,
                "predicted_distance": jnp.sqrt(sq), "from_model": jnp.ones(num, bool),
                "discarded": (wanted & ~rollout).sum(dtype=jnp.int32)}
        if self.anchoring == "auto":
            info["both_behaviors"] = jnp.stack([flat(y)[:, :-1] for y in both])
        # No parents: an imagined candidate's parent may be an imagined skill, not one of `repertoire`'s.
        return Proposal(flat(pools.actions), rollout, info,
                        features=flat(features) if self.keeps_features(task) else None)
