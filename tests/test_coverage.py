import jax.numpy as jnp
import numpy as np
import pytest
from compiled import compiled

from mqd_jax.core import coverage


def _coverage(centres, radius, reachable=None, resolution=256):
    low, high = np.zeros(2), np.ones(2)
    reach = np.ones((resolution, resolution), bool) if reachable is None else reachable
    grid = coverage.empty(low, high, reach, radius)
    c = jnp.asarray(centres, jnp.float32)
    grid = compiled(coverage.stamp)(grid, c, jnp.ones(len(c), jnp.int32), jnp.float32(radius))
    return float(compiled(coverage.fraction)(grid)), grid


def test_one_disk():
    value, _ = _coverage([[0.5, 0.5]], 0.2)
    assert value == pytest.approx(np.pi * 0.04, abs=0.01)


def test_disk_cut_by_the_border():
    # Centred on the left wall: half a disk.
    value, _ = _coverage([[0.0, 0.5]], 0.2)
    assert value == pytest.approx(np.pi * 0.04 / 2, abs=0.01)


def test_two_overlapping_disks_lens():
    r, d = 0.15, 0.1
    lens = 2 * r**2 * np.arccos(d / (2 * r)) - d / 2 * np.sqrt(4 * r**2 - d**2)
    value, _ = _coverage([[0.4, 0.5], [0.5, 0.5]], r)
    assert value == pytest.approx(2 * np.pi * r**2 - lens, abs=0.01)


def test_reachable_area_is_the_denominator():
    g = 256
    reach = np.zeros((g, g), bool)
    reach[: g // 2] = True  # left half of the box (first axis is x)
    value, _ = _coverage([[0.25, 0.5]], 0.1, reach)
    assert value == pytest.approx(np.pi * 0.01 / 0.5, abs=0.01)


def test_unstamp_undoes_stamp_and_overlaps_count():
    _, grid = _coverage([[0.3, 0.3], [0.32, 0.3]], 0.05)
    grid = coverage.stamp(grid, jnp.asarray([[0.3, 0.3]]), -jnp.ones(1, jnp.int32), jnp.float32(0.05))
    value = float(coverage.fraction(grid))
    assert value == pytest.approx(np.pi * 0.0025, abs=0.002)
    assert int(grid.counts.min()) >= 0


def test_matches_fine_monte_carlo_on_random_disks():
    rng = np.random.default_rng(1)
    centres = rng.random((300, 2))
    r = 0.02
    value, _ = _coverage(centres, r)
    pts = rng.random((200_000, 2))
    d2 = ((pts[:, None, :] - centres[None]) ** 2).sum(-1).min(1)
    assert value == pytest.approx((d2 <= r * r).mean(), abs=0.01)
