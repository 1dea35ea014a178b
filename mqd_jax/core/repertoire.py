"""The unstructured skill repertoire: its data, its nearest-skill searches and `insert`.

Insertion is the paper's rule (`mqd_jax.core.insertion`: one decision step, computed for a generation in
data-parallel rounds) after a search of each candidate's nearest skills within t_dist (`mqd_jax.core.bands`);
`insert` then writes the outcome and brings novelty up to date. Skills are never deleted, so the valid entries
are always the prefix `[0, count)`, and the searches and writes work on the smallest prefix that holds them
(`mqd_jax.core.prefix`). The rule's types, `AddStatus` and `Insertion`, are also importable from here.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from mqd_jax.core import bands, neighbours, prefix, pytree
from mqd_jax.core.insertion import AddStatus, Insertion, parallel_rule, replaced

__all__ = ["NUM_NEAR", "AddStatus", "Insertion", "Repertoire", "insert", "k_nearest", "nearest", "written_slots"]

# Nearest pre-generation skills (within t_dist) listed per candidate before the rule (`insert`'s num_near).
NUM_NEAR = 4


@pytree.dataclass
class Repertoire:
    """A fixed-capacity repertoire of C skills (a = action, b = behavior, q = quality).

    Attributes:
      actions: [C, n]; behaviors: [C, d]; qualities: [C]; novelty: [C].
      valid: [C] bool, equal to `arange(C) < count` (entries fill a prefix).
      count: int32 scalar, number of skills.
      neighbours: nearest-neighbour lists that give `novelty`.
      features: [C, f] the task's features of each skill's action (`Task.features`), kept where the emitter
        asks (`Emitter.keeps_features`: M-QD's model reads them), so that they are computed once per skill;
        f = 0 otherwise. Written with the actions, at the slots insertion picks.
    """

    actions: jax.Array
    behaviors: jax.Array
    qualities: jax.Array
    novelty: jax.Array
    valid: jax.Array
    count: jax.Array
    neighbours: neighbours.NeighbourLists
    features: jax.Array

    @classmethod
    def empty(cls, capacity: int, action_dim: int, behavior_dim: int, list_length: int,
              feature_dim: int = 0) -> Repertoire:
        return cls(
            actions=jnp.zeros((capacity, action_dim), jnp.float32),
            behaviors=jnp.zeros((capacity, behavior_dim), jnp.float32),
            qualities=jnp.zeros((capacity,), jnp.float32),
            novelty=jnp.zeros((capacity,), jnp.float32),
            valid=jnp.zeros((capacity,), bool),
            count=jnp.int32(0),
            neighbours=neighbours.NeighbourLists.empty(capacity, list_length),
            features=jnp.zeros((capacity, feature_dim), jnp.float32),
        )

    @property
    def capacity(self) -> int:
        return self.qualities.shape[0]


def nearest(rep: Repertoire, values: jax.Array, queries: jax.Array, exact: bool = True,
            min_prefix: int = 512) -> tuple[jax.Array, jax.Array]:
    """Squared distance [N] and slot [N] of the skill whose row of `values` [C, D] (a per-slot array: behaviors,
    or actions in some units) is nearest to each query [N, D]; inf and slot 0 for an empty repertoire.

    Searched on the smallest prefix of C / 2^j slots (at least `min_prefix`) that holds every skill, like
    `insert`'s search: the cost follows the repertoire's size, not C. `exact=False` computes the distances
    with a matrix product (`neighbours.sq_dists_by_product`): faster in many dimensions, nearly as exact.
    """
    distances = neighbours.sq_dists if exact else neighbours.sq_dists_by_product

    def search(size: int, values: jax.Array, valid: jax.Array, queries: jax.Array) -> tuple[jax.Array, jax.Array]:
        d = jnp.where(valid[:size][None], distances(queries, values[:size]), jnp.inf)
        slot = jnp.argmin(d, axis=1)
        return jnp.take_along_axis(d, slot[:, None], axis=1)[:, 0], slot.astype(jnp.int32)

    return prefix.on_prefix(prefix.prefix_sizes(rep.capacity, min_prefix), rep.count, search, values, rep.valid,
                            queries)


def k_nearest(rep: Repertoire, queries: jax.Array, k: int, min_prefix: int = 512) -> tuple[jax.Array, jax.Array]:
    """Squared distances [N, k] (ascending) and slots [N, k] of the k skills whose behaviors are nearest to each
    query behavior [N, d], ties to the lower slot; where fewer than k skills exist (or a query is NaN) the
    missing entries are inf (NaN) with slot -1. Searched on a prefix like `nearest`."""
    return prefix.on_prefix(prefix.prefix_sizes(rep.capacity, min_prefix), rep.count,
                            functools.partial(bands.nearest_before, k), rep, queries)


def apply(k: int, chunk: int, size: int, rep: Repertoire, behaviors: jax.Array, qualities: jax.Array,
           ins: Insertion) -> Repertoire:
    """Writes the rule's outcome into the first `size` slots (all but actions) and brings novelty up to date."""
    part = prefix.prefix(rep, size, rep.capacity)
    slot = written_slots(ins, size)
    count = rep.count + (ins.status == AddStatus.ADDED).sum(dtype=jnp.int32)
    valid = jnp.arange(size) < count
    new_behaviors = part.behaviors.at[slot].set(behaviors, mode="drop")
    lists = neighbours.update(part.neighbours, new_behaviors, valid, replaced(ins.victim_slot, size), slot, k, chunk)
    part = part.replace(
        behaviors=new_behaviors,
        qualities=part.qualities.at[slot].set(qualities, mode="drop"),
        novelty=neighbours.novelty(lists, valid, k),
        valid=valid,
        count=count,
        neighbours=lists,
    )
    return jax.tree.map(lambda x, y: x.at[:y.shape[0]].set(y) if x.ndim else y, rep, part)


def written_slots(ins: Insertion, capacity: int) -> jax.Array:
    """[P] the slot each candidate's skill ends in, or `capacity` (out of range) if it is not in the repertoire."""
    return jnp.where(ins.alive, ins.slot, capacity)


def insert(rep: Repertoire, actions: jax.Array, behaviors: jax.Array, qualities: jax.Array, usable: jax.Array,
           t_dist: jax.Array, k: int, num_near: int, chunk: int, min_prefix: int = 512,
           features: jax.Array | None = None) -> tuple[Repertoire, Insertion]:
    """Inserts a generation of candidates and updates novelty.

    Args:
      rep: the repertoire before the generation.
      actions: [P, n], behaviors: [P, d], qualities: [P] of the candidates.
      usable: [P] candidates that were rolled out and returned a valid, finite
        result; the others are skipped.
      t_dist: distance threshold; k: novelty's K; num_near: M above; chunk: rows
        of neighbour lists updated at a time; min_prefix: see below.
      features: [P, f] the candidates' features, written with their actions where the repertoire keeps
        features (f > 0; required then).

    Returns:
      The new repertoire (novelty up to date) and what happened to each candidate.

    Skills fill a prefix of the arrays, so the nearest-skill search before the
    rule and the writes and neighbour lists after it work on the smallest
    prefix of C / 2^j slots (at least `min_prefix`) that holds every skill:
    their cost follows the repertoire's size, not C. Under `jax.vmap` the
    batch works on the prefix its largest repertoire needs, and its loops and
    rare branches run once for the batch (`mqd_jax.core.batching`).
    """
    capacity, pop = rep.capacity, behaviors.shape[0]
    sizes = prefix.prefix_sizes(capacity, min_prefix)
    # The actions and features are only written, at the slots the rule picks: they stay out of the prefix work.
    slim = rep.replace(actions=jnp.zeros((capacity, 0), rep.actions.dtype), features=jnp.zeros((capacity, 0)))
    ok, axis = bands.searched(behaviors, usable, t_dist)
    near_d, near_i = bands.near_within(num_near, min_prefix, slim, behaviors, ok, axis, t_dist)
    ins = parallel_rule(rep, behaviors, near_d, near_i, qualities, usable, t_dist, ok)
    new = prefix.on_prefix(sizes, jnp.minimum(rep.count + pop, capacity), functools.partial(apply, k, chunk), slim,
                     behaviors, qualities, ins)
    written = written_slots(ins, capacity)
    kept = rep.features
    if kept.shape[1]:
        if features is None or features.shape != (pop, kept.shape[1]):
            raise ValueError(f"the repertoire keeps {kept.shape[1]} features per skill: insert needs the candidates' "
                             f"features [{pop}, {kept.shape[1]}], got {None if features is None else features.shape}")
        kept = kept.at[written].set(features.astype(kept.dtype), mode="drop")
    return new.replace(actions=rep.actions.at[written].set(actions, mode="drop"), features=kept), ins
