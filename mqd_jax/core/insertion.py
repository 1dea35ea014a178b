"""The paper's insertion rule (Algorithm 1), computed in data-parallel rounds.

Candidates are processed one after another, each against the repertoire as it stands after the previous ones:
farther than t_dist from the nearest skill, it is added; otherwise it replaces that nearest skill if its quality
is strictly higher; otherwise it is rejected. Of skills equally near a candidate, the nearest is the one in the
lowest slot (as a scan over the slots finds it), whether it was there before the generation or written in it.

`parallel_rule` computes every candidate's step at once, round after round, until nothing changes; the earlier
candidates a step reads are only those within t_dist, found in a grid of cells (`grid`), so no [P, P] matrix is
formed. Each step is `decide`, which the sequential rule one candidate at a time (the oracle, in the tests) shares.
"""

from __future__ import annotations

import enum
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import batching, grid, neighbours, prefix, pytree

# A repertoire (`mqd_jax.core.repertoire.Repertoire`, which imports this module) is read by its fields.
Repertoire = Any


class AddStatus(enum.IntEnum):
    """What insertion did with a candidate (`Insertion.status`, int32 arrays of these values)."""

    SKIPPED = 0  # not rolled out, or its rollout was invalid
    ADDED = 1  # a new niche: farther than t_dist from every skill
    REPLACED = 2  # took the place of its nearest skill, whose quality it beat
    REJECTED = 3  # within t_dist of a skill at least as good
    DROPPED_FULL = 4  # a new niche that did not fit: the repertoire was full


@pytree.dataclass
class Insertion:
    """What one generation's insertion did, per candidate (P candidates).

    Attributes:
      status: [P] int32, an `AddStatus` value.
      slot: [P] slot a candidate was written to (meaningful for ADDED/REPLACED).
      alive: [P] whether the candidate is still in the repertoire at the end.
      archived: [P] whether an archive entry came out of this candidate's step;
        the entry is the candidate itself (REJECTED, DROPPED_FULL) or the skill
        it replaced, given by `victim_slot` (>= 0, a pre-generation skill) or
        `victim_candidate` (>= 0, an earlier candidate of the generation).
      rounds: int32 scalar, the data-parallel rounds the rule took (`parallel_rule`; the sequential rule: P).
    """

    status: jax.Array
    slot: jax.Array
    alive: jax.Array
    victim_slot: jax.Array
    victim_candidate: jax.Array
    rounds: jax.Array

    @property
    def archived(self) -> jax.Array:
        return ((self.status == AddStatus.REJECTED) | (self.status == AddStatus.DROPPED_FULL)
                | (self.status == AddStatus.REPLACED))


def decide(nearest_is_new: jax.Array, d_new: jax.Array, slot_new: jax.Array, q_new: jax.Array, d_old: jax.Array,
           slot_old: jax.Array, q_old: jax.Array, quality: jax.Array, usable: jax.Array, count: jax.Array,
           size: jax.Array, capacity: int, t2: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The rule's step for a candidate (or each of several, elementwise), given its nearest skill: the one written
    earlier in the generation (squared distance d_new, slot, quality) where `nearest_is_new`, else the
    pre-generation one (d_old, slot_old, q_old); its quality and `usable`; `count` skills added before it to a
    repertoire of `size` skills and `capacity` slots; t2 = t_dist^2. Returns its status (int32 `AddStatus`), the
    slot it is written to or nearest (int32) and whether it replaces that skill. The parallel rule's rounds and
    the sequential oracle (the tests') share it."""
    d_nearest = jnp.where(nearest_is_new, d_new, d_old)
    q_nearest = jnp.where(nearest_is_new, q_new, q_old)
    is_new = d_nearest > t2
    full = size + count >= capacity
    replace = usable & ~is_new & (quality > q_nearest)
    status = jnp.select([~usable, is_new & ~full, is_new, replace],
                        [AddStatus.SKIPPED, AddStatus.ADDED, AddStatus.DROPPED_FULL, AddStatus.REPLACED],
                        AddStatus.REJECTED).astype(jnp.int32)
    slot = jnp.where(status == AddStatus.ADDED, size + count, jnp.where(nearest_is_new, slot_new, slot_old))
    return status, slot.astype(jnp.int32), replace


def replaced(victim_slot: jax.Array, size: int) -> jax.Array:
    """[size] mask of the pre-generation slots in victim_slot[P] (-1: none)."""
    return jnp.zeros(size, bool).at[jnp.where(victim_slot >= 0, victim_slot, size)].set(True, mode="drop")


def first_at(targets: jax.Array, size: int) -> jax.Array:
    """[size] the first (lowest) candidate i whose targets[i] names each index (-1: none), or P if none does."""
    pop = targets.shape[0]
    return jnp.full(size, pop, jnp.int32).at[jnp.where(targets >= 0, targets, size)].min(
        jnp.arange(pop, dtype=jnp.int32), mode="drop")


# The candidates `search_remaining` searches at a time: a round reads [SEARCH_ROWS, C] distances per step of
# its search, so [P, C] only when every candidate needs one.
SEARCH_ROWS = 64


def search_remaining(need_all: jax.Array, removed_at: jax.Array, behaviors: jax.Array, rep: Repertoire,
                      quick: tuple[jax.Array, ...]) -> tuple[jax.Array, ...]:
    """`quick` (squared distance, slot, quality of each candidate's nearest pre-generation skill [P]) where
    need_all[P] is False; elsewhere those of the nearest pre-generation skill that no candidate before it replaced
    (removed_at[C]: the first candidate that replaced each slot, P if none), searched SEARCH_ROWS candidates at a
    time (`batching.for_each_chunk`)."""
    def search(rows: jax.Array, found: tuple[jax.Array, ...], behaviors: jax.Array, rep: Repertoire,
               removed_at: jax.Array) -> tuple[jax.Array, ...]:
        there = rep.valid[None] & (removed_at[None] >= rows[:, None])
        d = jnp.where(there, neighbours.sq_dists(behaviors[rows], rep.behaviors), jnp.inf)
        d, j = neighbours.min_with_index(d, jnp.broadcast_to(jnp.arange(rep.capacity), d.shape))
        return tuple(x.at[rows].set(y, mode="drop") for x, y in zip(found, (d, j, rep.qualities[j]), strict=True))

    return batching.for_each_chunk(need_all, SEARCH_ROWS, search, quick, behaviors, rep, removed_at)


def rounds(rep: Repertoire, behaviors: jax.Array, near_d: jax.Array, near_i: jax.Array, cols: jax.Array,
            dists: jax.Array, qualities: jax.Array, usable: jax.Array, t_dist: jax.Array) -> Insertion:
    """`parallel_rule`'s rounds, given for each candidate the earlier candidates within t_dist of it: cols [P, K]
    (any order, every such candidate among them) and their squared distances dists [P, K] (inf elsewhere)."""
    capacity, pop = rep.capacity, behaviors.shape[0]
    t2 = t_dist**2
    cands = jnp.arange(pop, dtype=jnp.int32)
    near_q = rep.qualities[jnp.maximum(near_i, 0)]

    def step(s: Insertion) -> Insertion:
        """Every candidate's step, given the outcomes `s` of the candidates before it."""
        added = (s.status == AddStatus.ADDED).astype(jnp.int32)
        count = jnp.cumsum(added) - added  # skills added before each candidate
        lives = (s.status == AddStatus.ADDED) | (s.status == AddStatus.REPLACED)
        killed_at = first_at(s.victim_candidate, pop)  # the candidate that replaced each one (P: none)
        removed_at = first_at(s.victim_slot, capacity)  # the candidate that replaced each pre-generation skill
        # The nearest pre-generation skill still there: the first listed one not replaced by an earlier candidate,
        # else a full search (all M listed were replaced and the next one may be within t_dist).
        still_there = (near_i >= 0) & (removed_at[jnp.maximum(near_i, 0)] >= cands[:, None])
        first = jnp.argmax(still_there, axis=1)
        take = lambda x: jnp.take_along_axis(x, first[:, None], axis=1)[:, 0]  # noqa: E731
        quick = (jnp.where(still_there.any(1), take(near_d), jnp.inf), take(near_i), take(near_q))
        need_all = ~still_there.any(1) & (near_d[:, -1] <= t2)
        d_old, slot_old, q_old = search_remaining(need_all, removed_at, behaviors, rep, quick)
        # The nearest skill within t_dist written earlier in the generation, the lowest slot among equally near.
        alive = jnp.isfinite(dists) & lives[cols] & (killed_at[cols] >= cands[:, None])
        d_row = jnp.where(alive, dists, jnp.inf)
        d_new = d_row.min(axis=1)
        pick = jnp.argmin(jnp.where(alive & (d_row == d_new[:, None]), s.slot[cols], capacity), axis=1)
        j_new = jnp.take_along_axis(cols, pick[:, None], axis=1)[:, 0]
        slot_new = s.slot[j_new]
        nearest_is_new = jnp.isfinite(d_new) & ((d_new < d_old) | ((d_new == d_old) & (slot_new < slot_old)))
        j_new = jnp.where(nearest_is_new, j_new, -1)  # a function of the earlier candidates' outcomes only
        status, slot, replace = decide(nearest_is_new, d_new, slot_new, qualities[jnp.maximum(j_new, 0)], d_old,
                                       slot_old, q_old, qualities, usable, count, rep.count, capacity, t2)
        return Insertion(
            status=status,
            slot=slot,
            alive=(status == AddStatus.ADDED) | replace,
            victim_slot=jnp.where(replace & ~nearest_is_new, slot_old, -1).astype(jnp.int32),
            victim_candidate=jnp.where(replace & nearest_is_new, j_new, -1).astype(jnp.int32),
            rounds=s.rounds + 1,
        )

    def changed(carry: tuple[Insertion, Insertion]) -> jax.Array:
        a, b = carry
        return jnp.any(jnp.stack([jnp.any(x != y) for x, y in zip(jax.tree.leaves(a.replace(rounds=0)),
                                                                   jax.tree.leaves(b.replace(rounds=0)), strict=True)]))

    none = jnp.full(pop, -1, jnp.int32)
    start = Insertion(status=jnp.zeros(pop, jnp.int32), slot=jnp.zeros(pop, jnp.int32), alive=jnp.zeros(pop, bool),
                      victim_slot=none, victim_candidate=none, rounds=jnp.int32(0))
    # The first round runs inside the loop too: on the constant start, XLA would fold its reductions at compile
    # time, element by element (minutes at P = 1024).
    _, ins = jax.lax.while_loop(changed, lambda c: (c[1], step(c[1])), (start.replace(status=none), start))
    return ins.replace(alive=ins.alive & (first_at(ins.victim_candidate, pop) == pop))


# The narrowest run `parallel_rule` reads of the grid's cells (`grid.in_cells`); wider ones are 4x, 16x, ... it.
MIN_RUN = 16


def parallel_rule(rep: Repertoire, behaviors: jax.Array, near_d: jax.Array, near_i: jax.Array,
                   qualities: jax.Array, usable: jax.Array, t_dist: jax.Array, ok: jax.Array) -> Insertion:
    """The sequential rule's outcome, computed in data-parallel rounds (module doc): rep the repertoire before the
    generation; behaviors [P, d], qualities [P], usable [P] the candidates'; near_d, near_i [P, M] each
    candidate's M nearest pre-generation skills, ascending (squared distance, slot; inf and -1 where there are
    fewer; `bands.near_within`); ok: `bands.searched`'s (the candidates searched for).

    Every candidate's step is a function of the outcomes of the candidates before it. A round computes every
    candidate's step at once from the previous round's outcomes (the first round: from none); the outcomes
    that did not change are a fixed point, and the only one: the first candidate whose outcome would differ
    from the sequential rule's sees only correct predecessors, so its step is the sequential one. After round
    r at least the first r candidates are settled; in practice a generation settles in a few rounds, as only
    candidates within 2 t_dist of each other (a shared nearest skill, or one nearest the other) and the running
    count of added skills (slots, a full repertoire) link them. Of the earlier candidates, a step reads only
    those within t_dist, found once per generation in a grid of cells (`grid`): 3 runs of W places per
    candidate, W the smallest of MIN_RUN * 4^j (or P) that holds the longest run, so a round costs O(P (M + W))
    and no [P, P] matrix is formed. Returns the outcome (`Insertion.slot` is meaningful where the candidate is
    alive at the end; `rounds`: the rounds taken, the last one the check that nothing changes).
    """
    pop = behaviors.shape[0]
    cells = grid.cells(behaviors, ok, t_dist)

    def rule(width: int, rep: Repertoire, behaviors: jax.Array, near_d: jax.Array, near_i: jax.Array,
             qualities: jax.Array, usable: jax.Array, cells: grid.Cells, t_dist: jax.Array) -> Insertion:
        cols, there = grid.in_cells(width, cells)
        d = sum((behaviors[:, None, k] - behaviors[cols, k]) ** 2 for k in range(behaviors.shape[1]))
        earlier = there & (cols < jnp.arange(pop)[:, None]) & (d <= t_dist**2)
        # One buffer of distances, read by every round alike (a recomputation could round otherwise).
        dists = jax.lax.optimization_barrier(jnp.where(earlier, d, jnp.inf))
        return rounds(rep, behaviors, near_d, near_i, cols, dists, qualities, usable, t_dist)

    return prefix.on_prefix(prefix.window_sizes(pop, MIN_RUN), cells.longest, rule, rep, behaviors, near_d, near_i,
                            qualities, usable, cells, t_dist)
