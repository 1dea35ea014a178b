"""Exact nearest neighbours in behavior space, and the novelty they give.

Novelty of a skill (paper, "Quality-Diversity Search") is the mean Euclidean
distance to its K nearest repertoire neighbours. Recomputing it densely costs
O(capacity^2) per generation, which a CPU cannot afford, so each skill keeps a
list of its nearest neighbours that stays exact under the few changes a
generation makes:

* every list holds up to L = K + slack neighbours, in ascending order, and a
  *certainty radius* r: every other skill closer than r is in the list
  (r = inf: every other skill is in it);
* a replaced skill is removed from the lists that hold it; the list stays
  exact (its radius still holds), only shorter;
* a new skill is merged into the lists whose radius it falls inside;
* a list is recomputed from scratch only for new skills and for lists that
  removals left with fewer than K certain neighbours.

All distances are squared until novelty takes the square root.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mqd_jax.core import batching, pytree

_BLOCK = 32


def sq_dists(a: jax.Array, b: jax.Array) -> jax.Array:
    """Squared Euclidean distances between rows: a[M, d], b[N, d] -> [M, N]."""
    return sum((a[:, None, i] - b[None, :, i]) ** 2 for i in range(a.shape[1]))


def sq_dists_by_product(a: jax.Array, b: jax.Array) -> jax.Array:
    """`sq_dists` as ||a||^2 + ||b||^2 - 2 a.b^T: one matrix product, much faster for many dimensions, with
    rounding errors of order eps * ||a|| * ||b||: for finding near rows, not for exact thresholds."""
    product = jnp.matmul(a, b.T, precision=jax.lax.Precision.HIGHEST)
    return jnp.maximum((a * a).sum(1)[:, None] + (b * b).sum(1)[None] - 2.0 * product, 0.0)


def min_with_index(values: jax.Array, ids: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The smallest entry of each row of values[R, N] and its id (ids[R, N]; ties: the smaller id), in one
    reduction: a minimum found apart from its position could be matched against a recomputed row, rounded
    otherwise (XLA may fuse a distance matrix into each consumer, contracting multiply-adds in one and not the
    other), and then match none. NaN entries are passed over; a row without a number gives (inf, int32 max).
    Slower on a CPU than a minimum and a match (a variadic reduction)."""
    def smaller(a: tuple[jax.Array, jax.Array], b: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
        take_a = (a[0] < b[0]) | ((a[0] == b[0]) & (a[1] < b[1])) | jnp.isnan(b[0])
        return jnp.where(take_a, a[0], b[0]), jnp.where(take_a, a[1], b[1])

    init = (jnp.array(jnp.inf, values.dtype), jnp.array(jnp.iinfo(jnp.int32).max, jnp.int32))
    return jax.lax.reduce((values, jnp.broadcast_to(ids, values.shape).astype(jnp.int32)), init, smaller, (1,))


def _matched(values: jax.Array, ids: jax.Array, m: jax.Array, sel: jax.Array) -> tuple[jax.Array, jax.Array]:
    """`min_with_index` where a row's minimum `m` matched none of its entries (sel: int32 max), else (m, sel)."""
    exact, found = min_with_index(values, ids)
    missed = (sel == jnp.iinfo(jnp.int32).max) & jnp.isfinite(m)
    return jnp.where(missed, exact, m), jnp.where(missed, found, sel)


def k_smallest_of(values: jax.Array, ids: jax.Array, k: int) -> tuple[jax.Array, jax.Array]:
    """The k smallest entries of each row of values[R, N], ascending, with their ids[R, N] (distinct within a
    row), in k rounds of min-extraction; ties go to the smaller id; missing entries (inf) get id -1.

    A minimum, then the smallest id of the entries equal to it; where XLA recomputed a fused input for the match,
    rounded otherwise, so that a finite minimum matches no entry, that round takes `min_with_index` (rare: the
    values are then passed whole, computed once).
    """
    big = jnp.iinfo(jnp.int32).max

    def extract(values: jax.Array, _: None) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
        m = values.min(axis=1)
        sel = jnp.where(values == m[:, None], ids, big).min(axis=1)
        m, sel = batching.rare_cond(((sel == big) & jnp.isfinite(m)).any(), _matched, lambda v, i, m, s: (m, s),
                                    values, ids, m, sel)
        return jnp.where(ids == sel[:, None], jnp.inf, values), (m, jnp.where(jnp.isfinite(m), sel, -1))

    # A loop, not k copies of the pass: the program (and its compile time) stays the size of one pass.
    _, (out_v, out_i) = jax.lax.scan(extract, values, None, length=k)
    return out_v.T, out_i.T


def k_smallest(values: jax.Array, k: int) -> tuple[jax.Array, jax.Array]:
    """The k smallest entries of each row of values[R, N], ascending, with their columns.

    Exact, ties broken by the smaller column; missing entries (inf) get column -1.
    The k smallest lie in the k blocks of columns with the smallest minima, so
    only those k * 32 columns are searched.
    """
    r, n = values.shape
    cols = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32), (r, n))
    if n <= 4 * k * _BLOCK:
        return k_smallest_of(values, cols, k)
    pad = -n % _BLOCK
    values = jnp.pad(values, ((0, 0), (0, pad)), constant_values=jnp.inf)
    blocks = values.reshape(r, -1, _BLOCK)
    block_ids = jnp.broadcast_to(jnp.arange(blocks.shape[1], dtype=jnp.int32), blocks.shape[:2])
    _, chosen = k_smallest_of(blocks.min(axis=2), block_ids, k)
    # Rows with fewer than k finite blocks get -1: read block 0, keep none of it.
    picked = jnp.take_along_axis(blocks, jnp.maximum(chosen, 0)[:, :, None], axis=1)
    picked = jnp.where(chosen[:, :, None] >= 0, picked, jnp.inf).reshape(r, -1)
    picked_cols = (chosen[:, :, None] * _BLOCK + jnp.arange(_BLOCK)).reshape(r, -1)
    return k_smallest_of(picked, picked_cols.astype(jnp.int32), k)


@pytree.dataclass
class NeighbourLists:
    """Per-skill nearest-neighbour lists over a repertoire of capacity C.

    Attributes:
      sq_dist: [C, L] squared distances, ascending among finite entries; inf marks
        an empty place (removals leave holes).
      index: [C, L] int32 slot of each neighbour, -1 for an empty place.
      radius: [C] squared certainty radius: every skill closer than it is listed.
    """

    sq_dist: jax.Array
    index: jax.Array
    radius: jax.Array

    @classmethod
    def empty(cls, capacity: int, length: int) -> NeighbourLists:
        return cls(
            sq_dist=jnp.full((capacity, length), jnp.inf, jnp.float32),
            index=jnp.full((capacity, length), -1, jnp.int32),
            radius=jnp.full((capacity,), jnp.inf, jnp.float32),
        )

    @property
    def length(self) -> int:
        return self.sq_dist.shape[1]


def _recompute(lists: NeighbourLists, rows: jax.Array, d: jax.Array) -> NeighbourLists:
    """Rebuilds the lists of `rows` from their distances d[len(rows), C] to every skill (inf: none)."""
    v, i = k_smallest(d, lists.length + 1)
    return NeighbourLists(
        sq_dist=lists.sq_dist.at[rows].set(v[:, :-1], mode="drop"),
        index=lists.index.at[rows].set(i[:, :-1], mode="drop"),
        radius=lists.radius.at[rows].set(v[:, -1], mode="drop"),
    )


def _rebuild(rows: jax.Array, lists: NeighbourLists, behaviors: jax.Array, valid: jax.Array) -> NeighbourLists:
    """Rebuilds the lists of `rows` by a search over every skill (behaviors[C, d], valid[C])."""
    d = sq_dists(behaviors[rows], behaviors)
    return _recompute(lists, rows, jnp.where(valid[None] & (rows[:, None] != jnp.arange(valid.shape[0])), d, jnp.inf))


def _merge(rows: jax.Array, lists: NeighbourLists, behaviors: jax.Array, new_slots: jax.Array) -> NeighbourLists:
    """Merges into the lists of `rows` the new skills (at new_slots[P]; C: none) inside their radius."""
    capacity = behaviors.shape[0]
    d = sq_dists(behaviors[rows], behaviors[jnp.minimum(new_slots, capacity - 1)])  # [R, P]
    d = jnp.where((new_slots < capacity)[None] & (d < lists.radius[rows][:, None]), d, jnp.inf)
    v = jnp.concatenate([lists.sq_dist[rows], d], axis=1)
    i = jnp.concatenate([lists.index[rows], jnp.broadcast_to(new_slots, d.shape)], 1)
    v, i = k_smallest_of(v, jnp.where(jnp.isfinite(v), i, jnp.iinfo(jnp.int32).max), lists.length + 1)
    return NeighbourLists(
        sq_dist=lists.sq_dist.at[rows].set(v[:, :-1], mode="drop"),
        index=lists.index.at[rows].set(i[:, :-1], mode="drop"),
        radius=lists.radius.at[rows].set(jnp.minimum(lists.radius[rows], v[:, -1]), mode="drop"),
    )


def update(
    lists: NeighbourLists,
    behaviors: jax.Array,
    valid: jax.Array,
    removed: jax.Array,
    new_slots: jax.Array,
    k: int,
    chunk: int,
) -> NeighbourLists:
    """Brings the lists up to date after a generation's insertions.

    Distances are computed a chunk of rows at a time where they are needed;
    the new skills' distances to every skill only feed one reduction (which
    lists a new skill falls inside). Stored [P, C] matrices, batched over a
    sweep's runs, no longer fit in cache.

    Args:
      lists: lists exact for the repertoire before the generation.
      behaviors: [C, d] behaviors after the generation; valid: [C] their mask.
      removed: [C] slots whose previous skill was replaced this generation.
      new_slots: [P] slot of each new skill; C for a candidate that is not one.
      k: the novelty's K; chunk: rows processed at a time.
    """
    capacity = valid.shape[0]
    gone = (lists.index >= 0) & removed[jnp.maximum(lists.index, 0)]
    lists = lists.replace(sq_dist=jnp.where(gone, jnp.inf, lists.sq_dist), index=jnp.where(gone, -1, lists.index))
    changed = jnp.zeros_like(valid).at[new_slots].set(True, mode="drop")

    # Other skills whose certainty radius a new skill falls inside take it into their list.
    d_new = sq_dists(behaviors[jnp.minimum(new_slots, capacity - 1)], behaviors)  # [P, C]
    hit = valid & ~changed & ((new_slots < capacity)[:, None] & (d_new < lists.radius[None])).any(0)
    lists = batching.for_each_chunk(hit, chunk, _merge, lists, behaviors, new_slots)

    # New skills, and lists that removals left with fewer than k certain neighbours: recomputed.
    certain = jnp.isfinite(lists.sq_dist).sum(1)
    rebuild = valid & (changed | ((certain < k) & jnp.isfinite(lists.radius)))
    return batching.for_each_chunk(rebuild, chunk, _rebuild, lists, behaviors, valid)


def novelty(lists: NeighbourLists, valid: jax.Array, k: int) -> jax.Array:
    """[C] mean distance to the k nearest listed neighbours (fewer if fewer exist; 0 if none)."""
    finite = jnp.isfinite(lists.sq_dist)
    take = finite & (jnp.cumsum(finite, axis=1) <= k)
    total = jnp.where(take, jnp.sqrt(jnp.where(take, lists.sq_dist, 0.0)), 0.0).sum(1)
    return jnp.where(valid, total / jnp.maximum(take.sum(1), 1), 0.0)
