"""The spatial search before insertion: each candidate's nearest skills within t_dist, found in bands along one
behavior axis, so that no [P, C] matrix is formed for a large generation (every skill within t_dist of a
candidate lies in its band; what lies beyond does not change the insertion rule's outcome).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import grid, neighbours, prefix

# A repertoire (`mqd_jax.core.repertoire.Repertoire`, which imports this module) is read by its fields.
Repertoire = Any

# The narrowest window of the band searches (`bands`); wider ones are 4x, 16x, ... it, up to the whole set.
MIN_WINDOW = 64


def axis(points: jax.Array, ok: jax.Array, t_dist: jax.Array) -> jax.Array:
    """The behavior axis along which a band 2 t_dist wide holds the fewest of points [P, d] (those ok [P]) at
    most (`grid.crowding`)."""
    return jnp.argmin(grid.crowding(points, ok, t_dist)).astype(jnp.int32)


def searched(behaviors: jax.Array, usable: jax.Array, t_dist: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The candidates the searches look for (usable, finite behaviors) [P], and the axis of the skills' bands."""
    ok = usable & jnp.isfinite(behaviors).all(axis=1)
    return ok, axis(behaviors, ok, t_dist)


def bands(queries: jax.Array, query_ok: jax.Array, rows: jax.Array, row_ok: jax.Array, axis: jax.Array,
           t_dist: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Each query's band of rows: the rows whose coordinate on `axis` is within t_dist of the query's (with a
    margin for rounding), and so every row within t_dist of it. queries [P, d] (query_ok [P]), rows [N, d]
    (row_ok [N]; the others sort last, in no band). Returns (the rows in order along the axis [N], the first
    and the end sorted place of each band [P] (empty for a query not ok), the widest band's length)."""
    values = jnp.where(row_ok, jnp.take(rows, axis, axis=1), jnp.inf)
    coordinate = jnp.take(queries, axis, axis=1)
    scale = jnp.maximum(jnp.where(row_ok, jnp.abs(values), 0.0).max(),
                        jnp.where(query_ok, jnp.abs(coordinate), 0.0).max())
    half = grid.margined(t_dist, scale, 8)
    order = jnp.argsort(values, stable=True)
    ordered = values[order]
    lo = jnp.searchsorted(ordered, coordinate - half, "left")
    hi = jnp.where(query_ok, jnp.searchsorted(ordered, coordinate + half, "right"), lo)
    return order, lo, hi, (hi - lo).max()


def in_band(width: int, queries: jax.Array, rows: jax.Array, order: jax.Array, lo: jax.Array, hi: jax.Array
             ) -> tuple[jax.Array, jax.Array]:
    """(squared distances [P, width] of the rows in each query's band to the query, inf past the band's end; the
    rows' ids [P, width]), the band read `width` sorted places from its start (width >= the widest band)."""
    places = lo[:, None] + jnp.arange(width)
    ids = order[jnp.minimum(places, order.shape[0] - 1)]
    d = sum((queries[:, None, k] - rows[ids, k]) ** 2 for k in range(queries.shape[1]))
    return jnp.where(places < hi[:, None], d, jnp.inf), ids


# Below this many candidate-skill pairs, `near_within` reads every skill (no sorting, which a CPU does slowly).
BRUTE_FORCE_PAIRS = 1 << 20


def near_within(num_near: int, min_prefix: int, rep: Repertoire, behaviors: jax.Array, ok: jax.Array,
                 axis: jax.Array, t_dist: jax.Array) -> tuple[jax.Array, jax.Array]:
    """[P, M] squared distances and slots of each candidate's M nearest skills, ascending, ties to the lower slot
    (inf and -1 where there are fewer), among the skills in its band along `axis` (`bands`; every skill if the
    repertoire's prefix is small). Every skill within t_dist is in the band, so the entries within t_dist are
    those of the M nearest of all skills; what lies beyond t_dist does not change the insertion rule's outcome
    (a skill farther than t_dist is as good as none). ok [P]: the candidates to search for."""
    def search(size: int, rep: Repertoire, behaviors: jax.Array, ok: jax.Array, axis: jax.Array,
               t_dist: jax.Array) -> tuple[jax.Array, jax.Array]:
        if behaviors.shape[0] * size <= BRUTE_FORCE_PAIRS:
            return nearest_before(num_near, size, rep, behaviors)
        part = prefix.prefix(rep, size, rep.capacity)
        order, lo, hi, widest = bands(behaviors, ok, part.behaviors, part.valid, axis, t_dist)
        return prefix.on_prefix(prefix.window_sizes(size, MIN_WINDOW), widest,
                          lambda width, *a: neighbours.k_smallest_of(*in_band(width, *a), num_near),
                          behaviors, part.behaviors, order, lo, hi)

    return prefix.on_prefix(prefix.prefix_sizes(rep.capacity, min_prefix), rep.count, search, rep, behaviors, ok, axis,
                            t_dist)


def nearest_before(num_near: int, size: int, rep: Repertoire, behaviors: jax.Array) -> tuple[jax.Array, jax.Array]:
    """[P, M] squared distances and slots of each candidate's M nearest skills, searched in the first `size` slots."""
    part = prefix.prefix(rep, size, rep.capacity)
    return neighbours.k_smallest(jnp.where(part.valid[None], neighbours.sq_dists(behaviors, part.behaviors), jnp.inf),
                                 num_near)
