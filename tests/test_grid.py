"""The grid of cells that finds points within t_dist of each other (`mqd_jax.core.grid`), against brute force."""

import jax.numpy as jnp
import numpy as np
import pytest
from compiled import compiled

from mqd_jax.core import grid


@pytest.mark.parametrize("dim", [1, 2, 5])
def test_runs_as_long_as_the_longest_hold_every_pair_within_t_dist(dim):
    """Clustered points far from the origin (rounding), exact duplicates, pairs at exactly t_dist on a lattice and
    points not ok: with runs read as long as the longest, every pair within t_dist is found, none not ok, never a
    point itself; with shorter runs, only pairs that are there."""
    rng = np.random.default_rng(dim)
    t_dist = 0.05
    lattice = 1000.0 + t_dist * rng.integers(0, 6, (40, dim))  # pairs exactly t_dist apart
    clusters = 1000.0 + rng.random((3, dim)) * 0.3
    near = clusters[rng.integers(0, 3, 200)] + 0.02 * rng.normal(size=(200, dim))
    points = np.concatenate([lattice, near, near[:10]]).astype(np.float32)
    ok = rng.random(len(points)) > 0.1
    cells = compiled(grid.cells)(jnp.asarray(points), jnp.asarray(ok), jnp.float32(t_dist))
    d = np.sqrt(((points[:, None].astype(np.float64) - points[None]) ** 2).sum(-1))
    within = (d <= np.float32(t_dist)) & ok[:, None] & ok[None] & ~np.eye(len(points), dtype=bool)
    for width, exact in ((int(cells.longest), True), (2, False)):
        ids, there = map(np.asarray, compiled(grid.in_cells)(width, cells))
        found = np.zeros_like(within)
        rows = np.repeat(np.arange(len(points)), ids.shape[1]).reshape(ids.shape)
        found[rows[there], ids[there]] = True
        assert not (found & ~(ok[:, None] & ok[None])).any() and not found[np.eye(len(points), dtype=bool)].any()
        if exact:
            assert not (within & ~found).any() and within.sum() > 100
        else:
            assert (within & ~found).any()  # the runs are longer than 2 here: some pairs unseen
