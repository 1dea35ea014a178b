"""The unstructured skill repertoire and the paper's sequential insertion rule.

Insertion (paper, "Quality-Diversity Search" and Algorithm 1): candidates are
processed one after another, each against the repertoire as it stands after the
previous ones. If its behavior is farther than t_dist from the nearest skill it
is added; otherwise it replaces that nearest skill if its quality is strictly
higher; otherwise it is rejected. Skills are never deleted, so the valid
entries are always the prefix `[0, count)`. Ties: of skills equally near a
candidate, the nearest is the one in the lowest slot (as a scan over the slots
finds it), whether it was there before the generation or written in it.

Speed (`_parallel_rule`): every candidate's step is computed at once, round after round, until
nothing changes; the skills and the earlier candidates a step reads are only those within t_dist,
found once per generation in bands along one behavior axis (`_bands`), so the rule forms no [P, P]
or [P, C] matrix for a large generation (the neighbour lists' update still measures the new skills
against every skill). The sequential rule (`_sequential_rule`) is the oracle.
"""

from __future__ import annotations

import enum
import functools
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import batching, grid, neighbours, pytree

# Nearest pre-generation skills (within t_dist) listed per candidate before the rule (`insert`'s num_near).
NUM_NEAR = 4


class AddStatus(enum.IntEnum):
    """What insertion did with a candidate (`Insertion.status`, int32 arrays of these values)."""

    SKIPPED = 0  # not rolled out, or its rollout was invalid
    ADDED = 1  # a new niche: farther than t_dist from every skill
    REPLACED = 2  # took the place of its nearest skill, whose quality it beat
    REJECTED = 3  # within t_dist of a skill at least as good
    DROPPED_FULL = 4  # a new niche that did not fit: the repertoire was full


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
      rounds: int32 scalar, the data-parallel rounds the rule took (`_parallel_rule`; the sequential rule: P).
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


def _replaced(victim_slot: jax.Array, size: int) -> jax.Array:
    """[size] mask of the pre-generation slots in victim_slot[P] (-1: none)."""
    return jnp.zeros(size, bool).at[jnp.where(victim_slot >= 0, victim_slot, size)].set(True, mode="drop")


def _nearest_remaining(behavior: jax.Array, behaviors: jax.Array, valid: jax.Array, qualities: jax.Array,
                       victim_slot: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Squared distance, slot and quality of the pre-generation skill nearest to behavior[d] among those
    victim_slot[P] has not replaced (inf if there is none); behaviors: [C, d], valid, qualities: [C]."""
    d = jnp.where(valid & ~_replaced(victim_slot, valid.shape[0]),
                  neighbours.sq_dists(behavior[None], behaviors), jnp.inf)
    d, j = neighbours.min_with_index(d, jnp.arange(valid.shape[0])[None])
    return d[0], j[0], qualities[j[0]]


def _sequential_rule(rep: Repertoire, behaviors: jax.Array, near_d: jax.Array, near_i: jax.Array,
                     d_cand: jax.Array, qualities: jax.Array, usable: jax.Array, t_dist: jax.Array) -> Insertion:
    """Runs the insertion rule candidate by candidate; writes nothing yet.

    near_d, near_i: [P, M] each candidate's M nearest pre-generation skills,
    ascending (squared distance, slot; inf and -1 where there are fewer);
    d_cand: [P, P] squared distances between candidates; usable: [P] the
    candidates to insert. The loop's state is O(P), so it batches well under vmap.
    """
    capacity, pop = rep.capacity, d_cand.shape[0]
    t2 = t_dist**2
    near_q = rep.qualities[jnp.maximum(near_i, 0)]
    cands = jnp.arange(pop)

    def step(i: jax.Array, s: Insertion) -> Insertion:
        count = (s.status == AddStatus.ADDED).sum()
        # The nearest pre-generation skill still there: the first listed one not replaced, else a full search.
        listed = near_i[i]
        still_there = (listed >= 0) & ~(listed[:, None] == s.victim_slot[None]).any(1)
        first = jnp.argmax(still_there)
        quick = (jnp.where(still_there.any(), near_d[i, first], jnp.inf), listed[first], near_q[i, first])
        # All M listed skills were replaced and the next one may be within t_dist.
        need_all = ~still_there.any() & (near_d[i, -1] <= t2)
        d_old, slot_old, q_old = batching.rare_cond(
            need_all, lambda *a: _nearest_remaining(*a[:-1]), lambda *a: a[-1],
            behaviors[i], rep.behaviors, rep.valid, rep.qualities, s.victim_slot, quick)
        # The nearest skill written earlier in this generation, the lowest slot among equally near ones.
        d_row = jnp.where(s.alive, d_cand[i], jnp.inf)
        d_new = d_row.min()
        j_new = jnp.argmin(jnp.where(d_row == d_new, s.slot, capacity))
        slot_new = s.slot[j_new]
        # Nearest by (distance, slot), as a scan over the repertoire's slots would find.
        nearest_is_new = (d_new < d_old) | ((d_new == d_old) & (slot_new < slot_old))
        d_nearest = jnp.where(nearest_is_new, d_new, d_old)
        q_nearest = jnp.where(nearest_is_new, qualities[jnp.maximum(j_new, 0)], q_old)
        is_new = d_nearest > t2
        full = rep.count + count >= capacity
        replace = usable[i] & ~is_new & (qualities[i] > q_nearest)
        status = jnp.select(
            [~usable[i], is_new & ~full, is_new, replace],
            [AddStatus.SKIPPED, AddStatus.ADDED, AddStatus.DROPPED_FULL, AddStatus.REPLACED], AddStatus.REJECTED)
        slot_i = jnp.where(status == AddStatus.ADDED, rep.count + count,
                           jnp.where(nearest_is_new, slot_new, slot_old))
        # Whole-row selects rather than scatters: P is small, and they batch without a gather.
        at_i = cands == i
        return Insertion(
            status=jnp.where(at_i, status, s.status),
            slot=jnp.where(at_i, slot_i, s.slot),
            alive=jnp.where(at_i, (status == AddStatus.ADDED) | replace,
                            s.alive & ~((cands == j_new) & replace & nearest_is_new)),
            victim_slot=jnp.where(at_i, jnp.where(replace & ~nearest_is_new, slot_old, -1), s.victim_slot),
            victim_candidate=jnp.where(at_i, jnp.where(replace & nearest_is_new, j_new, -1), s.victim_candidate),
            rounds=s.rounds + 1,
        )

    none = jnp.full(pop, -1, jnp.int32)
    init = Insertion(status=jnp.zeros(pop, jnp.int32), slot=jnp.zeros(pop, jnp.int32), alive=jnp.zeros(pop, bool),
                     victim_slot=none, victim_candidate=none, rounds=jnp.int32(0))
    return jax.lax.fori_loop(0, pop, step, init)


def _first_at(targets: jax.Array, size: int) -> jax.Array:
    """[size] the first (lowest) candidate i whose targets[i] names each index (-1: none), or P if none does."""
    pop = targets.shape[0]
    return jnp.full(size, pop, jnp.int32).at[jnp.where(targets >= 0, targets, size)].min(
        jnp.arange(pop, dtype=jnp.int32), mode="drop")


# The candidates `_search_remaining` searches at a time: a round reads [SEARCH_ROWS, C] distances per step of
# its search, so [P, C] only when every candidate needs one.
SEARCH_ROWS = 64


def _search_remaining(need_all: jax.Array, removed_at: jax.Array, behaviors: jax.Array, rep: Repertoire,
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


def _rounds(rep: Repertoire, behaviors: jax.Array, near_d: jax.Array, near_i: jax.Array, cols: jax.Array,
            dists: jax.Array, qualities: jax.Array, usable: jax.Array, t_dist: jax.Array) -> Insertion:
    """`_parallel_rule`'s rounds, given for each candidate the earlier candidates within t_dist of it: cols [P, K]
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
        killed_at = _first_at(s.victim_candidate, pop)  # the candidate that replaced each one (P: none)
        removed_at = _first_at(s.victim_slot, capacity)  # the candidate that replaced each pre-generation skill
        # The nearest pre-generation skill still there: the first listed one not replaced by an earlier candidate,
        # else a full search (all M listed were replaced and the next one may be within t_dist).
        still_there = (near_i >= 0) & (removed_at[jnp.maximum(near_i, 0)] >= cands[:, None])
        first = jnp.argmax(still_there, axis=1)
        take = lambda x: jnp.take_along_axis(x, first[:, None], axis=1)[:, 0]  # noqa: E731
        quick = (jnp.where(still_there.any(1), take(near_d), jnp.inf), take(near_i), take(near_q))
        need_all = ~still_there.any(1) & (near_d[:, -1] <= t2)
        d_old, slot_old, q_old = _search_remaining(need_all, removed_at, behaviors, rep, quick)
        # The nearest skill within t_dist written earlier in the generation, the lowest slot among equally near.
        alive = jnp.isfinite(dists) & lives[cols] & (killed_at[cols] >= cands[:, None])
        d_row = jnp.where(alive, dists, jnp.inf)
        d_new = d_row.min(axis=1)
        pick = jnp.argmin(jnp.where(alive & (d_row == d_new[:, None]), s.slot[cols], capacity), axis=1)
        j_new = jnp.take_along_axis(cols, pick[:, None], axis=1)[:, 0]
        slot_new = s.slot[j_new]
        nearest_is_new = jnp.isfinite(d_new) & ((d_new < d_old) | ((d_new == d_old) & (slot_new < slot_old)))
        j_new = jnp.where(nearest_is_new, j_new, -1)  # a function of the earlier candidates' outcomes only
        d_nearest = jnp.where(nearest_is_new, d_new, d_old)
        q_nearest = jnp.where(nearest_is_new, qualities[jnp.maximum(j_new, 0)], q_old)
        is_new = d_nearest > t2
        full = rep.count + count >= capacity
        replace = usable & ~is_new & (qualities > q_nearest)
        status = jnp.select([~usable, is_new & ~full, is_new, replace],
                            [AddStatus.SKIPPED, AddStatus.ADDED, AddStatus.DROPPED_FULL, AddStatus.REPLACED],
                            AddStatus.REJECTED).astype(jnp.int32)
        return Insertion(
            status=status,
            slot=jnp.where(status == AddStatus.ADDED, rep.count + count, jnp.where(nearest_is_new, slot_new, slot_old)
                           ).astype(jnp.int32),
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
    return ins.replace(alive=ins.alive & (_first_at(ins.victim_candidate, pop) == pop))


# The narrowest window of the band searches (`_bands`); wider ones are 4x, 16x, ... it, up to the whole set.
MIN_WINDOW = 64


def _window_sizes(size: int, narrowest: int) -> list[int]:
    """The window lengths a search over `size` sorted rows chooses from, ascending: narrowest * 4^j up to half of
    size, and size (each length is a copy of the search in the program): MIN_WINDOW for the skills' bands,
    MIN_RUN for the runs of the candidates' grid cells."""
    return [*(narrowest * 4**j for j in range(size.bit_length()) if 2 * narrowest * 4**j <= size), size]


def _axis(points: jax.Array, ok: jax.Array, t_dist: jax.Array) -> jax.Array:
    """The behavior axis along which a band 2 t_dist wide holds the fewest of points [P, d] (those ok [P]) at
    most (`grid.crowding`)."""
    return jnp.argmin(grid.crowding(points, ok, t_dist)).astype(jnp.int32)


def _searched(behaviors: jax.Array, usable: jax.Array, t_dist: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The candidates the searches look for (usable, finite behaviors) [P], and the axis of the skills' bands."""
    ok = usable & jnp.isfinite(behaviors).all(axis=1)
    return ok, _axis(behaviors, ok, t_dist)


def _bands(queries: jax.Array, query_ok: jax.Array, rows: jax.Array, row_ok: jax.Array, axis: jax.Array,
           t_dist: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Each query's band of rows: the rows whose coordinate on `axis` is within t_dist of the query's (with a
    margin for rounding), and so every row within t_dist of it. queries [P, d] (query_ok [P]), rows [N, d]
    (row_ok [N]; the others sort last, in no band). Returns (the rows in order along the axis [N], the first
    and the end sorted place of each band [P] (empty for a query not ok), the widest band's length)."""
    values = jnp.where(row_ok, jnp.take(rows, axis, axis=1), jnp.inf)
    coordinate = jnp.take(queries, axis, axis=1)
    scale = jnp.maximum(jnp.where(row_ok, jnp.abs(values), 0.0).max(),
                        jnp.where(query_ok, jnp.abs(coordinate), 0.0).max())
    half = t_dist * 1.001 + 8 * jnp.finfo(jnp.float32).eps * scale
    order = jnp.argsort(values, stable=True)
    ordered = values[order]
    lo = jnp.searchsorted(ordered, coordinate - half, "left")
    hi = jnp.where(query_ok, jnp.searchsorted(ordered, coordinate + half, "right"), lo)
    return order, lo, hi, (hi - lo).max()


def _in_band(width: int, queries: jax.Array, rows: jax.Array, order: jax.Array, lo: jax.Array, hi: jax.Array
             ) -> tuple[jax.Array, jax.Array]:
    """(squared distances [P, width] of the rows in each query's band to the query, inf past the band's end; the
    rows' ids [P, width]), the band read `width` sorted places from its start (width >= the widest band)."""
    places = lo[:, None] + jnp.arange(width)
    ids = order[jnp.minimum(places, order.shape[0] - 1)]
    d = sum((queries[:, None, k] - rows[ids, k]) ** 2 for k in range(queries.shape[1]))
    return jnp.where(places < hi[:, None], d, jnp.inf), ids


# Below this many candidate-skill pairs, `_near_within` reads every skill (no sorting, which a CPU does slowly).
BRUTE_FORCE_PAIRS = 1 << 20


def _near_within(num_near: int, min_prefix: int, rep: Repertoire, behaviors: jax.Array, ok: jax.Array,
                 axis: jax.Array, t_dist: jax.Array) -> tuple[jax.Array, jax.Array]:
    """[P, M] squared distances and slots of each candidate's M nearest skills, ascending, ties to the lower slot
    (inf and -1 where there are fewer), among the skills in its band along `axis` (`_bands`; every skill if the
    repertoire's prefix is small). Every skill within t_dist is in the band, so the entries within t_dist are
    those of the M nearest of all skills; what lies beyond t_dist does not change the insertion rule's outcome
    (a skill farther than t_dist is as good as none). ok [P]: the candidates to search for."""
    def search(size: int, rep: Repertoire, behaviors: jax.Array, ok: jax.Array, axis: jax.Array,
               t_dist: jax.Array) -> tuple[jax.Array, jax.Array]:
        if behaviors.shape[0] * size <= BRUTE_FORCE_PAIRS:
            return _nearest_before(num_near, size, rep, behaviors)
        part = _prefix(rep, size, rep.capacity)
        order, lo, hi, widest = _bands(behaviors, ok, part.behaviors, part.valid, axis, t_dist)
        return _on_prefix(_window_sizes(size, MIN_WINDOW), widest,
                          lambda width, *a: neighbours.k_smallest_of(*_in_band(width, *a), num_near),
                          behaviors, part.behaviors, order, lo, hi)

    return _on_prefix(_prefix_sizes(rep.capacity, min_prefix), rep.count, search, rep, behaviors, ok, axis, t_dist)


# The narrowest run `_parallel_rule` reads of the grid's cells (`grid.in_cells`); wider ones are 4x, 16x, ... it.
MIN_RUN = 16


def _parallel_rule(rep: Repertoire, behaviors: jax.Array, near_d: jax.Array, near_i: jax.Array,
                   qualities: jax.Array, usable: jax.Array, t_dist: jax.Array, ok: jax.Array) -> Insertion:
    """The sequential rule's outcome (`_sequential_rule`'s arguments but d_cand), computed in data-parallel rounds;
    ok: `_searched`'s (the candidates searched for).

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
        return _rounds(rep, behaviors, near_d, near_i, cols, dists, qualities, usable, t_dist)

    return _on_prefix(_window_sizes(pop, MIN_RUN), cells.longest, rule, rep, behaviors, near_d, near_i, qualities,
                      usable, cells, t_dist)


def _prefix(tree: Repertoire, size: int, capacity: int) -> Repertoire:
    """The per-slot arrays of `tree` cut to their first `size` slots."""
    return jax.tree.map(lambda x: x[:size] if x.ndim and x.shape[0] == capacity else x, tree)


def _on_prefix(sizes: Sequence[int], needed: jax.Array, fn: Callable[..., Any], *operands: Any) -> Any:
    """fn(size, *operands) for the smallest of `sizes` (ascending) that is >= needed (capped at the last).

    `fn` must give the same result for every size >= needed; under vmap the
    batch then shares the size its largest member needs (`batching.switch_largest`).
    """
    index = jnp.searchsorted(jnp.asarray(sizes), jnp.minimum(needed, sizes[-1]))
    return batching.switch_largest(index, [functools.partial(fn, size) for size in sizes], *operands)


def _prefix_sizes(capacity: int, min_prefix: int) -> list[int]:
    """The prefix sizes C / 2^j (at least `min_prefix`, at most C) that prefix work chooses from, ascending."""
    return sorted({max(capacity >> j, min(min_prefix, capacity)) for j in range(capacity.bit_length())})


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

    return _on_prefix(_prefix_sizes(rep.capacity, min_prefix), rep.count, search, values, rep.valid, queries)


def k_nearest(rep: Repertoire, queries: jax.Array, k: int, min_prefix: int = 512) -> tuple[jax.Array, jax.Array]:
    """Squared distances [N, k] (ascending) and slots [N, k] of the k skills whose behaviors are nearest to each
    query behavior [N, d], ties to the lower slot; where fewer than k skills exist (or a query is NaN) the
    missing entries are inf (NaN) with slot -1. Searched on a prefix like `nearest`."""
    return _on_prefix(_prefix_sizes(rep.capacity, min_prefix), rep.count, functools.partial(_nearest_before, k), rep,
                      queries)


def _nearest_before(num_near: int, size: int, rep: Repertoire, behaviors: jax.Array) -> tuple[jax.Array, jax.Array]:
    """[P, M] squared distances and slots of each candidate's M nearest skills, searched in the first `size` slots."""
    part = _prefix(rep, size, rep.capacity)
    return neighbours.k_smallest(jnp.where(part.valid[None], neighbours.sq_dists(behaviors, part.behaviors), jnp.inf),
                                 num_near)


def _apply(k: int, chunk: int, size: int, rep: Repertoire, behaviors: jax.Array, qualities: jax.Array,
           ins: Insertion) -> Repertoire:
    """Writes the rule's outcome into the first `size` slots (all but actions) and brings novelty up to date."""
    part = _prefix(rep, size, rep.capacity)
    slot = written_slots(ins, size)
    count = rep.count + (ins.status == AddStatus.ADDED).sum(dtype=jnp.int32)
    valid = jnp.arange(size) < count
    new_behaviors = part.behaviors.at[slot].set(behaviors, mode="drop")
    lists = neighbours.update(part.neighbours, new_behaviors, valid, _replaced(ins.victim_slot, size), slot, k, chunk)
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
    sizes = _prefix_sizes(capacity, min_prefix)
    # The actions and features are only written, at the slots the rule picks: they stay out of the prefix work.
    slim = rep.replace(actions=jnp.zeros((capacity, 0), rep.actions.dtype), features=jnp.zeros((capacity, 0)))
    ok, axis = _searched(behaviors, usable, t_dist)
    near_d, near_i = _near_within(num_near, min_prefix, slim, behaviors, ok, axis, t_dist)
    ins = _parallel_rule(rep, behaviors, near_d, near_i, qualities, usable, t_dist, ok)
    new = _on_prefix(sizes, jnp.minimum(rep.count + pop, capacity), functools.partial(_apply, k, chunk), slim,
                     behaviors, qualities, ins)
    written = written_slots(ins, capacity)
    kept = rep.features
    if kept.shape[1]:
        if features is None or features.shape != (pop, kept.shape[1]):
            raise ValueError(f"the repertoire keeps {kept.shape[1]} features per skill: insert needs the candidates' "
                             f"features [{pop}, {kept.shape[1]}], got {None if features is None else features.shape}")
        kept = kept.at[written].set(features.astype(kept.dtype), mode="drop")
    return new.replace(actions=rep.actions.at[written].set(actions, mode="drop"), features=kept), ins
