"""Behavior-space coverage (paper, "Results: Building a repertoire"), in behavior spaces of any dimension d.

Each skill covers a ball of radius t_dist around its behavior; coverage is the
volume of the union of the balls inside the reachable part of the behavior box,
divided by the reachable volume. It is kept incrementally, as a count per point
of the balls that cover it, so a generation only stamps the balls of the skills
it added and unstamps those of the skills it replaced. The points are either

* `Grid`: the centres of a G^d grid of cells, G = `Config.coverage_resolution`
  (its square in one dimension: as many cells as in two; `axis_cells`);
  a ball is stamped on the (2 reach + 1)^d cells around it. Chosen when the grid
  and a generation's stamps fit the memory bounds (`MAX_GRID_CELLS`,
  `MAX_STAMP_CELLS`): every 2-D task at the default 256 cells per axis, 1-D tasks,
  3-D tasks at up to 161 cells per axis;
* `Samples`: `Config.coverage_samples` points drawn uniformly in the box (a fixed
  seed, so the same for every run of a config), a Monte Carlo estimate whose
  standard error is sqrt(c (1 - c) / n) for coverage c over n reachable points
  (`standard_error`). Chosen otherwise (d >= 4; d = 3 at the default resolution).

`method` says which a config gets; it is decided, and the memory checked, before
anything is allocated.
"""

from __future__ import annotations

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import pytree

GRID, MONTE_CARLO = "grid", "monte carlo"
MAX_GRID_CELLS = 2**22  # a grid's cells (int32 counts + bool reachable: 20 MiB per run)
MAX_STAMP_CELLS = 2**24  # cells a generation's stamps touch (skills x window), its temporaries' size
MIN_SAMPLES, MAX_SAMPLES = 2**10, 2**20  # Monte Carlo points (at most 36 MiB with d = 8)
SAMPLE_SEED = 0


@pytree.dataclass
class Grid:
    """Ball counts over the cells of the behavior box.

    Attributes:
      counts: [G] * d int32, number of balls covering each cell centre.
      reachable: [G] * d bool, cells whose centre is reachable.
      low, high: static, the behavior box (d floats each): compile-time
        constants, which makes stamping markedly faster than traced bounds.
      reach: static, the largest ball radius stamped, in cells.
    """

    counts: jax.Array
    reachable: jax.Array
    low: tuple[float, ...] = pytree.field(pytree_node=False)
    high: tuple[float, ...] = pytree.field(pytree_node=False)
    reach: int = pytree.field(pytree_node=False)


@pytree.dataclass
class Samples:
    """Ball counts over points drawn uniformly in the behavior box (a Monte Carlo estimate).

    Attributes:
      counts: [M] int32, number of balls covering each point.
      reachable: [M] bool, points that are reachable.
      points: [M, d] float32, the points.
    """

    counts: jax.Array
    reachable: jax.Array
    points: jax.Array


def cell_centres(low: np.ndarray, high: np.ndarray, resolution: int) -> np.ndarray:
    """[G] * d + [d] centres of the grid's cells (first axis: the first behavior dimension)."""
    axes = [lo + (np.arange(resolution) + 0.5) * (hi - lo) / resolution for lo, hi in zip(low, high, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def sample_points(low: np.ndarray, high: np.ndarray, samples: int) -> np.ndarray:
    """[samples, d] float32 points uniform in the box, the same for every call (seed `SAMPLE_SEED`)."""
    rng = np.random.default_rng(SAMPLE_SEED)
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    return (low + rng.random((samples, low.size)) * (high - low)).astype(np.float32)


def _reach(low: np.ndarray, high: np.ndarray, resolution: int, max_radius: float) -> int:
    cell = float(np.min((np.asarray(high) - np.asarray(low)) / resolution))
    return math.ceil(max_radius / cell) + 1


def axis_cells(d: int, resolution: int) -> int:
    """Cells per axis of a grid of `resolution` in d dimensions: `resolution`, squared in one dimension."""
    return resolution**2 if d == 1 else resolution


def method(low: np.ndarray, high: np.ndarray, resolution: int, max_radius: float, stamps: int) -> str:
    """`GRID` when a grid of `axis_cells`^d cells and `stamps` balls of radius up to `max_radius` a generation fit
    `MAX_GRID_CELLS` and `MAX_STAMP_CELLS`, else `MONTE_CARLO`. Decided before anything is allocated."""
    d = len(low)
    g = axis_cells(d, resolution)
    window = (2 * _reach(low, high, g, max_radius) + 1) ** d
    return GRID if g**d <= MAX_GRID_CELLS and stamps * window <= MAX_STAMP_CELLS else MONTE_CARLO


def empty(low: np.ndarray, high: np.ndarray, reachable: np.ndarray, max_radius: float) -> Grid:
    """A grid with no balls; `reachable` is [G] * d and balls are at most `max_radius`."""
    resolution = reachable.shape[0]
    return Grid(
        counts=jnp.zeros(reachable.shape, jnp.int32),
        reachable=jnp.asarray(reachable),
        low=tuple(float(x) for x in np.asarray(low, np.float32)),
        high=tuple(float(x) for x in np.asarray(high, np.float32)),
        reach=_reach(low, high, resolution, max_radius),
    )


def empty_samples(points: np.ndarray, reachable: np.ndarray) -> Samples:
    """Samples with no balls at `points` [M, d] whose reachability is `reachable` [M]."""
    return Samples(counts=jnp.zeros(len(points), jnp.int32), reachable=jnp.asarray(reachable, bool),
                   points=jnp.asarray(points, jnp.float32))


# Products and sums are kept apart (no fused multiply-add, which a compiler uses in one program and not another):
# a point on a ball's border is inside or not the same way in every program (e.g. sharded and whole runs).
def _apart(x: jax.Array) -> jax.Array:
    return jax.lax.optimization_barrier(x)


def _within(points: jax.Array, centres: jax.Array, radius: jax.Array) -> jax.Array:
    """[...] whether points [..., d] lie within `radius` of centres [..., d] (broadcast), the squares summed axis
    by axis in order."""
    terms = _apart((points - centres) ** 2)
    sq = terms[..., 0]
    for axis in range(1, terms.shape[-1]):
        sq = sq + terms[..., axis]
    return sq <= radius**2


def stamp(cover: Grid | Samples, centres: jax.Array, weights: jax.Array, radius: jax.Array) -> Grid | Samples:
    """Adds `weights[P]` (+1 stamp, -1 unstamp, 0 nothing) on the balls of `radius` around centres[P, d]."""
    if isinstance(cover, Samples):
        return _stamp_samples(cover, centres, weights, radius)
    g, d = cover.counts.shape[0], cover.counts.ndim
    low = jnp.asarray(cover.low, jnp.float32)
    size = (jnp.asarray(cover.high, jnp.float32) - low) / g
    window = np.asarray(list(itertools.product(range(-cover.reach, cover.reach + 1), repeat=d)), np.int32)
    base = jnp.floor((centres - low) / size).astype(jnp.int32)  # [P, d]
    index = base[:, None, :] + window[None]  # [P, W, d]
    cell = low + _apart((index + 0.5) * size)
    inside = _within(cell, centres[:, None], radius) & ((index >= 0) & (index < g)).all(axis=-1)
    inside &= weights[:, None] != 0
    flat = jnp.zeros(inside.shape, jnp.int32)
    for axis in range(d):
        flat = flat * g + index[..., axis]
    flat = jnp.where(inside, flat, g**d).reshape(-1)
    w = jnp.broadcast_to(weights[:, None], inside.shape).reshape(-1)
    counts = cover.counts.reshape(-1).at[flat].add(w, mode="drop").reshape(cover.counts.shape)
    return cover.replace(counts=counts)


def _stamp_samples(cover: Samples, centres: jax.Array, weights: jax.Array, radius: jax.Array) -> Samples:
    # One pass over the points per ball with a weight (most of a generation's have none: a candidate that was
    # not added, a slot that was not replaced), the balls with weights first.
    order = jnp.argsort(weights == 0, stable=True)

    def add(i: jax.Array, counts: jax.Array) -> jax.Array:
        ball = order[i]
        return counts + jnp.where(_within(cover.points, centres[ball], radius), weights[ball], 0)

    return cover.replace(counts=jax.lax.fori_loop(0, (weights != 0).sum(), add, cover.counts))


def fraction(cover: Grid | Samples) -> jax.Array:
    """Covered fraction of the reachable cells (or points)."""
    covered = ((cover.counts > 0) & cover.reachable).sum()
    # A constant denominator may be turned into a multiplication by its
    # reciprocal in one program and not another; the barrier keeps the result
    # the same in every compiled program (e.g. chunked vs whole runs).
    total = jax.lax.optimization_barrier(jnp.maximum(cover.reachable.sum(), 1))
    return covered / total


def standard_error(value: np.ndarray, reachable_points: int) -> np.ndarray:
    """The standard error sqrt(c (1 - c) / n) of Monte Carlo coverage estimates `value` over n reachable points."""
    value = np.asarray(value, np.float64)
    return np.sqrt(value * (1 - value) / max(reachable_points, 1))
