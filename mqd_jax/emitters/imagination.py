"""QD run inside the model: only what the imagined generations add is rolled out.

`ModelEmitter(inner, Imagination(generations=G), surrogate)` takes its proposal
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
the chain's predict stages (anchoring) are the `ModelEmitter`'s; a part that
keeps or replaces the first rows (a share, steering) is refused: the rows are not a ranking.
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
from mqd_jax.emitters.parts import ModelInfo, Part


def survivors(written: jax.Array, capacity: int) -> jax.Array:
    """written [G, P]: the slot each imagined candidate's skill ended its generation in (`capacity` if none) ->
    [G, P] bool, still there after the last generation (no later generation wrote its slot)."""
    g = written.shape[0]
    flat = written.reshape(-1)
    later = jnp.repeat(jnp.arange(g), written.shape[1])
    overwritten = ((flat[:, None] == flat[None, :]) & (later[None, :] > later[:, None])).any(axis=1)
    return ((flat < capacity) & ~overwritten).reshape(written.shape)


@dataclasses.dataclass(frozen=True)
class Imagination:
    """A source in a `ModelEmitter`'s rule slot: roll out what `generations` imagined generations of its inner
    emitter add (module doc).

    Attributes:
      generations: the imagined generations per real one.
    """

    generations: int = 3

    # Its rows are not a ranking: a part that keeps or replaces the first rows is refused.
    ranked = False

    def __post_init__(self) -> None:
        if not (is_int(self.generations) and self.generations >= 1):
            raise ValueError(f"Imagination.generations={self.generations!r} is invalid: expected an int >= 1")

    def check(self, emitter: Any) -> None:
        """ValueError where the emitter's chain has a part with a pool stage (imagined generations draw their own
        pools)."""
        pooled = [part for part in emitter.parts if type(part).pool is not Part.pool]
        if pooled:
            raise ValueError(f"ModelEmitter: {pooled[0]!r} is invalid with Imagination: its pool stage would not "
                             "run (imagined generations draw their own pools)")

    def pool_size(self, num: int) -> int:
        return num

    def propose(self, key: jax.Array, emitter: Any, state: Any, repertoire: Repertoire, task: Task, params: Params,
                num: int) -> Proposal:
        """The emitter's proposal of `num` rows: the first of the imagined candidates still in the imagined
        repertoire after the last imagined generation (module doc)."""
        view = emitter.view(state, repertoire, task, params, num)
        keeps = emitter.keeps_features(task)

        def imagine(rep: Repertoire, key: jax.Array) -> tuple[Repertoire, tuple[Any, ...]]:
            pool = emitter.inner.propose(key, state.inner, rep, task, params.part(params.emitter.inner), num)
            x = emitter.model.inputs(pool.actions, task)
            features = x[:, task.action_dim:] if keeps else x[:, :0]  # [num, 0]: none kept
            y, infos = emitter.predicted(state, pool.actions, pool.parents, x,
                                         dataclasses.replace(view, repertoire=rep))
            predicted = y.mean(axis=0)
            rep, ins = repertoire_lib.insert(rep, pool.actions, predicted[:, :-1], predicted[:, -1], pool.rollout,
                                             params.t_dist, emitter.k, repertoire_lib.NUM_NEAR, chunk=32,
                                             features=features)
            return rep, (pool, predicted, infos, repertoire_lib.written_slots(ins, rep.capacity), features)

        _, (pools, predicted, infos, written, features) = jax.lax.scan(
            imagine, repertoire, jax.random.split(key, self.generations))
        kept = survivors(written, repertoire.capacity).reshape(-1)
        rows = jnp.where(view.warm_up, jnp.arange(num), jnp.argsort(~kept, stable=True)[:num])
        flat = lambda x: x.reshape(-1, *x.shape[2:])[rows]  # noqa: E731  [G, num, ...] -> the kept rows [num, ...]
        wanted = flat(pools.rollout)
        rollout = jnp.where(view.warm_up, wanted, wanted & kept[rows])
        # The predicted distance to the nearest real skill: the opener AUC's score.
        behaviors = flat(predicted)[:, :-1]
        sq, _ = repertoire_lib.nearest(repertoire, repertoire.behaviors, behaviors)
        validity = emitter.model.usable(state.surrogate, flat(pools.actions), task)
        info = ModelInfo(jax.tree.map(flat, pools.info), behaviors, jnp.sqrt(sq), jnp.ones(num, bool),
                         (wanted & ~rollout).sum(dtype=jnp.int32), validity,
                         {name: ((), jax.tree.map(flat, info)) for name, info in infos.items()})
        # No parents: an imagined candidate's parent may be an imagined skill, not one of `repertoire`'s.
        return Proposal(flat(pools.actions), rollout, info, features=flat(features) if keeps else None)
