"""Behavior-space coverage (paper, "Results: Building a repertoire").

Each skill covers a disk of radius t_dist around its behavior; coverage is the
area of the union of the disks inside the reachable part of the behavior box,
divided by the reachable area. It is measured on a grid of G x G cells (cell
centres), kept incrementally: a count per cell of the disks that cover it, so a
generation only stamps the disks of the skills it added and unstamps those of
the skills it replaced.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import pytree


@pytree.dataclass
class CoverageGrid:
    """Disk counts over the behavior box.

    Attributes:
      counts: [G, G] int32, number of disks covering each cell centre.
      reachable: [G, G] bool, cells whose centre is reachable.
      low, high: static, the behavior box (2 floats each): compile-time
        constants, which makes stamping markedly faster than traced bounds.
      reach: static, the largest disk radius stamped, in cells.
    """

    counts: jax.Array
    reachable: jax.Array
    low: tuple[float, float] = pytree.field(pytree_node=False)
    high: tuple[float, float] = pytree.field(pytree_node=False)
    reach: int = pytree.field(pytree_node=False)


def cell_centres(low: np.ndarray, high: np.ndarray, resolution: int) -> np.ndarray:
    """[G, G, 2] centres of the grid's cells (first axis: x)."""
    axes = [lo + (np.arange(resolution) + 0.5) * (hi - lo) / resolution for lo, hi in zip(low, high, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def empty(low: np.ndarray, high: np.ndarray, reachable: np.ndarray, max_radius: float) -> CoverageGrid:
    """A grid with no disks; `reachable` is [G, G] and disks are at most `max_radius`."""
    resolution = reachable.shape[0]
    cell = float(np.min((np.asarray(high) - np.asarray(low)) / resolution))
    return CoverageGrid(
        counts=jnp.zeros(reachable.shape, jnp.int32),
        reachable=jnp.asarray(reachable),
        low=tuple(float(x) for x in np.asarray(low, np.float32)),
        high=tuple(float(x) for x in np.asarray(high, np.float32)),
        reach=math.ceil(max_radius / cell) + 1,
    )


def stamp(grid: CoverageGrid, centres: jax.Array, weights: jax.Array, radius: jax.Array) -> CoverageGrid:
    """Adds `weights[P]` (+1 stamp, -1 unstamp, 0 nothing) on the disks around centres[P, 2]."""
    g = grid.counts.shape[0]
    low = jnp.asarray(grid.low, jnp.float32)
    size = (jnp.asarray(grid.high, jnp.float32) - low) / g
    offsets = jnp.arange(-grid.reach, grid.reach + 1)
    base = jnp.floor((centres - low) / size).astype(jnp.int32)  # [P, 2]
    ix = base[:, 0, None, None] + offsets[None, :, None]  # [P, S, 1]
    iy = base[:, 1, None, None] + offsets[None, None, :]  # [P, 1, S]
    cx = low[0] + (ix + 0.5) * size[0]
    cy = low[1] + (iy + 0.5) * size[1]
    inside = ((cx - centres[:, 0, None, None]) ** 2 + (cy - centres[:, 1, None, None]) ** 2 <= radius**2)
    inside &= (ix >= 0) & (ix < g) & (iy >= 0) & (iy < g) & (weights[:, None, None] != 0)
    flat = jnp.where(inside, ix * g + iy, g * g).reshape(-1)
    w = jnp.broadcast_to(weights[:, None, None], inside.shape).reshape(-1)
    counts = grid.counts.reshape(-1).at[flat].add(w, mode="drop").reshape(g, g)
    return grid.replace(counts=counts)


def fraction(grid: CoverageGrid) -> jax.Array:
    """Covered fraction of the reachable cells."""
    covered = ((grid.counts > 0) & grid.reachable).sum()
    # A constant denominator may be turned into a multiplication by its
    # reciprocal in one program and not another; the barrier keeps the result
    # the same in every compiled program (e.g. chunked vs whole runs).
    total = jax.lax.optimization_barrier(jnp.maximum(grid.reachable.sum(), 1))
    return covered / total
