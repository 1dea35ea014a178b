"""The unstructured skill repertoire and the paper's sequential insertion rule.

Insertion (paper, "Quality-Diversity Search" and Algorithm 1): candidates are
processed one after another, each against the repertoire as it stands after the
previous ones. If its behavior is farther than t_dist from the nearest skill it
is added; otherwise it replaces that nearest skill if its quality is strictly
higher; otherwise it is rejected. Skills are never deleted, so the valid
entries are always the prefix `[0, count)`.

Speed: the repertoire only changes at the slots this generation writes, so the
nearest skill of a candidate is either one of its M nearest pre-generation
skills that is still there, or an earlier candidate of the generation. Both are
precomputed in batch; the sequential loop then does O(M + P) work per
candidate, and falls back to an exact O(C) search when all M were replaced.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from mqd_jax import neighbours

# Outcome of a candidate, in `Insertion.status`.
SKIPPED, ADDED, REPLACED, REJECTED, DROPPED_FULL = 0, 1, 2, 3, 4


@struct.dataclass
class Repertoire:
    """A fixed-capacity repertoire of C skills (a = action, b = behavior, q = quality).

    Attributes:
      actions: [C, n]; behaviors: [C, d]; qualities: [C]; novelty: [C].
      valid: [C] bool, equal to `arange(C) < count` (entries fill a prefix).
      count: int32 scalar, number of skills.
      neighbours: nearest-neighbour lists that give `novelty`.
    """

    actions: jax.Array
    behaviors: jax.Array
    qualities: jax.Array
    novelty: jax.Array
    valid: jax.Array
    count: jax.Array
    neighbours: neighbours.NeighbourLists

    @classmethod
    def empty(cls, capacity: int, action_dim: int, behavior_dim: int, list_length: int) -> Repertoire:
        return cls(
            actions=jnp.zeros((capacity, action_dim), jnp.float32),
            behaviors=jnp.zeros((capacity, behavior_dim), jnp.float32),
            qualities=jnp.zeros((capacity,), jnp.float32),
            novelty=jnp.zeros((capacity,), jnp.float32),
            valid=jnp.zeros((capacity,), bool),
            count=jnp.int32(0),
            neighbours=neighbours.NeighbourLists.empty(capacity, list_length),
        )

    @property
    def capacity(self) -> int:
        return self.qualities.shape[0]


@struct.dataclass
class Insertion:
    """What one generation's insertion did, per candidate (P candidates).

    Attributes:
      status: [P] int32, one of SKIPPED, ADDED, REPLACED, REJECTED, DROPPED_FULL.
      slot: [P] slot a candidate was written to (meaningful for ADDED/REPLACED).
      alive: [P] whether the candidate is still in the repertoire at the end.
      removed: [C] slots whose pre-generation skill was replaced.
      archived: [P] whether an archive entry came out of this candidate's step;
        the entry is the candidate itself (REJECTED, DROPPED_FULL) or the skill
        it replaced, given by `victim_slot` (>= 0, a pre-generation skill) or
        `victim_candidate` (>= 0, an earlier candidate of the generation).
    """

    status: jax.Array
    slot: jax.Array
    alive: jax.Array
    removed: jax.Array
    victim_slot: jax.Array
    victim_candidate: jax.Array

    @property
    def archived(self) -> jax.Array:
        return (self.status == REJECTED) | (self.status == DROPPED_FULL) | (self.status == REPLACED)


def _sequential_rule(rep: Repertoire, d_old: jax.Array, d_cand: jax.Array, qualities: jax.Array, ok: jax.Array,
                     t_dist: jax.Array, num_near: int) -> Insertion:
    """Runs the insertion rule candidate by candidate; writes nothing yet.

    d_old: [P, C] squared distances from candidates to the skills before the
    generation (inf for empty slots); d_cand: [P, P] between candidates.
    """
    capacity, pop = rep.capacity, d_cand.shape[0]
    t2 = t_dist**2
    near_d, near_i = neighbours.k_smallest(d_old, min(num_near, capacity))

    def nearest_old(i: jax.Array, removed: jax.Array) -> tuple[jax.Array, jax.Array]:
        usable = (near_i[i] >= 0) & ~removed[jnp.maximum(near_i[i], 0)]
        first = jnp.argmax(usable)

        def exhaustive() -> tuple[jax.Array, jax.Array]:
            d = jnp.where(removed, jnp.inf, d_old[i])
            j = jnp.argmin(d).astype(jnp.int32)
            return d[j], j

        # All M listed skills were replaced and the next one may be within t_dist.
        need_all = ~usable.any() & (near_d[i, -1] <= t2)
        quick = (jnp.where(usable.any(), near_d[i, first], jnp.inf), near_i[i, first])
        return jax.lax.cond(need_all, exhaustive, lambda: quick)

    def step(i: jax.Array, s: Insertion) -> Insertion:
        count = (s.status == ADDED).sum()
        d_o, j_o = nearest_old(i, s.removed)
        d_c_row = jnp.where(s.alive, d_cand[i], jnp.inf)
        j_c = jnp.argmin(d_c_row)
        d_c, slot_c = d_c_row[j_c], s.slot[j_c]
        # Nearest by (distance, slot), as a scan over the repertoire's slots would find.
        use_c = (d_c < d_o) | ((d_c == d_o) & (slot_c < j_o))
        d_n = jnp.where(use_c, d_c, d_o)
        q_n = jnp.where(use_c, qualities[j_c], rep.qualities[jnp.maximum(j_o, 0)])
        is_new = d_n > t2
        full = rep.count + count >= capacity
        replace = ok[i] & ~is_new & (qualities[i] > q_n)
        status = jnp.select(
            [~ok[i], is_new & ~full, is_new, replace],
            [SKIPPED, ADDED, DROPPED_FULL, REPLACED], REJECTED)
        slot_i = jnp.where(status == ADDED, rep.count + count, jnp.where(use_c, slot_c, j_o))
        return Insertion(
            status=s.status.at[i].set(status),
            slot=s.slot.at[i].set(slot_i),
            alive=s.alive.at[j_c].set(s.alive[j_c] & ~(replace & use_c))
                         .at[i].set((status == ADDED) | replace),
            removed=s.removed.at[jnp.maximum(j_o, 0)].set(s.removed[jnp.maximum(j_o, 0)] | (replace & ~use_c)),
            victim_slot=s.victim_slot.at[i].set(jnp.where(replace & ~use_c, j_o, -1)),
            victim_candidate=s.victim_candidate.at[i].set(jnp.where(replace & use_c, j_c, -1)),
        )

    init = Insertion(
        status=jnp.zeros(pop, jnp.int32), slot=jnp.zeros(pop, jnp.int32), alive=jnp.zeros(pop, bool),
        removed=jnp.zeros(capacity, bool), victim_slot=jnp.full(pop, -1, jnp.int32),
        victim_candidate=jnp.full(pop, -1, jnp.int32))
    return jax.lax.fori_loop(0, pop, step, init)


def _prefix(tree: Repertoire, size: int, capacity: int) -> Repertoire:
    """The per-slot arrays of `tree` cut to their first `size` slots."""
    return jax.tree.map(lambda x: x[:size] if x.ndim and x.shape[0] == capacity else x, tree)


def _write_prefix(full: Repertoire, part: Repertoire) -> Repertoire:
    return jax.tree.map(lambda x, y: x.at[:y.shape[0]].set(y) if x.ndim else y, full, part)


def insert(rep: Repertoire, actions: jax.Array, behaviors: jax.Array, qualities: jax.Array, ok: jax.Array,
           t_dist: jax.Array, k: int, num_near: int, chunk: int, min_prefix: int = 512
           ) -> tuple[Repertoire, Insertion]:
    """Inserts a generation of candidates and updates novelty.

    Skills fill a prefix of the arrays, so the work is done on the smallest
    prefix of C / 2^j slots (at least `min_prefix`) that can hold every skill
    after this generation: its cost follows the repertoire's size, not C.
    Under `jax.vmap` (seeds, hyperparameters) the batch's insertions run one
    after another: batched, the size-dependent branches and loops would all run
    for every member. See `insert_dense` for the arguments.
    """
    def run(rep: Repertoire, actions: jax.Array, behaviors: jax.Array, qualities: jax.Array, ok: jax.Array,
            t_dist: jax.Array) -> tuple[Repertoire, Insertion]:
        capacity, pop = rep.capacity, behaviors.shape[0]
        sizes = sorted({max(capacity >> j, min(min_prefix, capacity)) for j in range(capacity.bit_length())})

        def branch(size: int) -> Callable[[Repertoire], tuple[Repertoire, Insertion]]:
            def on_prefix(rep: Repertoire) -> tuple[Repertoire, Insertion]:
                part, ins = insert_dense(_prefix(rep, size, capacity), actions, behaviors, qualities, ok, t_dist,
                                         k, num_near, chunk)
                removed = jnp.zeros(capacity, bool).at[:size].set(ins.removed)
                return _write_prefix(rep, part), ins.replace(removed=removed)
            return on_prefix

        index = jnp.searchsorted(jnp.asarray(sizes), jnp.minimum(rep.count + pop, capacity))
        return jax.lax.switch(index, [branch(s) for s in sizes], rep)

    # The actions are only written, at the slots the rule picks, so they stay out of the in-turn part:
    # under vmap that part copies each member's arrays in and out, and the actions are the largest.
    no_actions = jnp.zeros((rep.capacity, 0), rep.actions.dtype)
    new, ins = _in_turn_under_vmap(run)(rep.replace(actions=no_actions), no_actions[:behaviors.shape[0]], behaviors,
                                        qualities, ok, t_dist)
    return new.replace(actions=rep.actions.at[_written(ins, rep.capacity)].set(actions, mode="drop")), ins


def _written(ins: Insertion, capacity: int) -> jax.Array:
    """[P] the slot each candidate's skill ends in, or `capacity` (out of range) if it is not in the repertoire."""
    return jnp.where(ins.alive, ins.slot, capacity)


def _in_turn_under_vmap(fn: Callable[..., Any]) -> Callable[..., Any]:
    """`fn`, whose vmap runs the batch's members one after another (`lax.map`) instead of batching its ops."""
    wrapped = jax.custom_batching.custom_vmap(fn)

    @wrapped.def_vmap
    def rule(axis_size: int, in_batched: Any, *args: Any) -> tuple[Any, Any]:
        args = jax.tree.map(lambda x, batched: x if batched else jnp.broadcast_to(x, (axis_size, *jnp.shape(x))),
                            args, tuple(in_batched))
        # `wrapped` again, so that an outer vmap (seeds x hyperparameters) also runs in turn.
        out = jax.lax.map(lambda a: wrapped(*a), args)
        return out, jax.tree.map(lambda _: True, out)

    return wrapped


def insert_dense(rep: Repertoire, actions: jax.Array, behaviors: jax.Array, qualities: jax.Array, ok: jax.Array,
                 t_dist: jax.Array, k: int, num_near: int, chunk: int) -> tuple[Repertoire, Insertion]:
    """Inserts a generation of candidates into all C slots and updates novelty.

    Args:
      rep: the repertoire before the generation.
      actions: [P, n], behaviors: [P, d], qualities: [P] of the candidates.
      ok: [P] candidates that were evaluated and returned a valid, finite result;
        the others are skipped.
      t_dist: distance threshold; k: novelty's K; num_near: M above; chunk: rows
        of neighbour lists updated at a time.

    Returns:
      The new repertoire (novelty up to date) and what happened to each candidate.
    """
    d_old = jnp.where(rep.valid[None], neighbours.sq_dists(behaviors, rep.behaviors), jnp.inf)
    d_cand = neighbours.sq_dists(behaviors, behaviors)
    ins = _sequential_rule(rep, d_old, d_cand, qualities, ok, t_dist, num_near)
    slot = _written(ins, rep.capacity)
    count = rep.count + (ins.status == ADDED).sum(dtype=jnp.int32)
    valid = jnp.arange(rep.capacity) < count
    new_behaviors = rep.behaviors.at[slot].set(behaviors, mode="drop")
    # Distances to the repertoire after the generation: the written columns now
    # hold candidates.
    d_new = d_old.at[:, slot].set(d_cand, mode="drop")
    lists = neighbours.update(rep.neighbours, new_behaviors, valid, d_new, ins.removed, slot, k, chunk)
    rep = Repertoire(
        actions=rep.actions.at[slot].set(actions, mode="drop"),
        behaviors=new_behaviors,
        qualities=rep.qualities.at[slot].set(qualities, mode="drop"),
        novelty=neighbours.novelty(lists, valid, k),
        valid=valid,
        count=count,
        neighbours=lists,
    )
    return rep, ins
