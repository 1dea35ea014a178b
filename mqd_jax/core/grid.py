"""Points within t_dist of each other, found in a grid of cells about t_dist wide without an [N, N] matrix.

The points are binned on their two least crowded behavior axes (`crowding`; the one axis in one dimension) and
sorted by cell. Every point within t_dist of a point lies in its cell or an adjacent one: three runs of the sorted
order (one in one dimension), each three cells long. `in_cells` reads `width` places of each run: exact where no
run holds more (`Cells.longest`), the rest of a longer run unseen. Used by the insertion's rounds (the earlier
candidates a candidate's step reads; exact, a width that holds the longest run) and by `Diverse`'s rounds (the
pool neighbours a candidate sees; a fixed width).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mqd_jax.core import pytree

# Cells per axis at most (ids stay int32); far points share the border cells: read, not lost.
SPAN = 2**15


def crowding(points: jax.Array, ok: jax.Array, t_dist: jax.Array) -> jax.Array:
    """[d] per behavior axis, the most of points [P, d] (those ok [P]) that a band 2 t_dist wide holds, estimated
    without sorting: P bins at least t_dist wide, and the most any 3 adjacent hold."""
    pop, dim = points.shape
    low = jnp.where(ok[:, None], points, jnp.inf).min(axis=0)
    spread = jnp.where(ok[:, None], points, -jnp.inf).max(axis=0) - low
    bin_width = jnp.maximum(t_dist, spread / pop)
    bins = jnp.clip(jnp.where(ok[:, None], (points - low) / bin_width, 0.0), 0, pop - 1).astype(jnp.int32)
    counts = jnp.zeros((dim, pop + 2), jnp.int32).at[jnp.arange(dim), bins + 1].add(ok[:, None].astype(jnp.int32))
    return (counts[:, :-2] + counts[:, 1:-1] + counts[:, 2:]).max(axis=1)


@pytree.dataclass
class Cells:
    """N points binned in the grid and sorted by cell.

    Attributes:
      order: [N] the points in cell order (those not ok last); ok: [N] the points binned.
      lo, hi: [R, N] the first and the end sorted place of each point's R runs of adjacent cells (R = 3, or 1 in
        one dimension; empty for a point not ok).
      longest: int32 scalar, the most points any run holds.
    """

    order: jax.Array
    ok: jax.Array
    lo: jax.Array
    hi: jax.Array
    longest: jax.Array


def margined(t_dist: jax.Array, scale: jax.Array, ulps: int) -> jax.Array:
    """t_dist widened for rounding: by 0.1% and by `ulps` float32 epsilons of `scale`, the largest coordinate's
    magnitude (distances and positions computed in float32 may differ by that much from exact ones)."""
    return t_dist * 1.001 + ulps * jnp.finfo(jnp.float32).eps * scale


def cells(points: jax.Array, ok: jax.Array, t_dist: jax.Array) -> Cells:
    """points [N, d] (those ok [N]) binned in cells a little wider than t_dist (a margin for rounding, so that
    points within t_dist are never two cells apart)."""
    dim = points.shape[1]
    if dim == 1:
        axes, offsets = jnp.zeros(2, jnp.int32), (0,)
    else:
        axes, offsets = jnp.argsort(crowding(points, ok, t_dist), stable=True)[:2].astype(jnp.int32), (-1, 0, 1)
    coordinates = jnp.take(points, axes, axis=1)
    low = jnp.where(ok[:, None], coordinates, jnp.inf).min(axis=0)
    scale = jnp.where(ok[:, None], jnp.abs(coordinates), 0.0).max()
    width = margined(t_dist, scale, 16)
    cell = jnp.clip(jnp.floor((coordinates - low) / width), 0, SPAN - 3).astype(jnp.int32)
    cell = jnp.where(ok[:, None], cell + 1, 0)
    none = jnp.iinfo(jnp.int32).max
    ids = jnp.where(ok, cell[:, 1] * SPAN + cell[:, 0] if dim > 1 else cell[:, 0], none)
    order = jnp.argsort(ids, stable=True)
    ordered = ids[order]
    centres = jnp.stack([ids + offset * SPAN for offset in offsets])
    lo = jnp.searchsorted(ordered, centres - 1, "left")
    hi = jnp.where(ok, jnp.searchsorted(ordered, centres + 1, "right"), lo)
    return Cells(order=order, ok=ok, lo=lo, hi=hi, longest=(hi - lo).max())


def in_cells(width: int, grid: Cells) -> tuple[jax.Array, jax.Array]:
    """(ids [N, R x width] of the points each point's runs hold, read `width` places of each run; whether each is
    one (bool: in the run, binned, not the point itself))."""
    size = grid.order.shape[0]
    places = grid.lo[:, :, None] + jnp.arange(width)
    ids = grid.order[jnp.minimum(places, size - 1)]
    there = (places < grid.hi[:, :, None]) & grid.ok[ids] & (ids != jnp.arange(size)[:, None])
    return jnp.concatenate(list(ids), axis=1), jnp.concatenate(list(there), axis=1)
