import itertools
import math

import numpy as np
import pytest

from mqd_jax.experiment.stats import bootstrap_interval, mann_whitney


def test_u_counts_the_pairs_a_wins_with_ties_as_halves():
    a, b = np.array([1.0, 2.0, 3.0, 4.0]), np.array([2.0, 5.0, 6.0])
    wins = sum((x > y) + 0.5 * (x == y) for x in a for y in b)  # brute force: 0.5 + 1 + 1 = 2.5
    u, _ = mann_whitney(a, b)
    assert u == wins == 2.5
    assert mann_whitney(b, a)[0] == len(a) * len(b) - u


def test_p_value_by_hand_without_ties():
    a, b = np.arange(10.0), np.arange(10.0) + 100.0  # completely separated, U = 0
    u, p = mann_whitney(a, b)
    z = (abs(0 - 50) - 0.5) / math.sqrt(10 * 10 * 21 / 12)
    assert u == 0 and p == pytest.approx(math.erfc(z / math.sqrt(2)), rel=1e-12)
    assert p < 1e-3
    assert mann_whitney(a, a)[1] == 1.0  # identical samples: no evidence
    with pytest.raises(ValueError, match="two non-empty samples"):
        mann_whitney(a, [])


def _all_resample_values(statistic, groups):
    """Brute force: the statistic of every resample (every choice of indices with replacement per group)."""
    choices = [itertools.product(range(len(g)), repeat=len(g)) for g in groups]
    return {statistic(*(g[list(idx)] for g, idx in zip(groups, picked, strict=True)))
            for picked in itertools.product(*[list(c) for c in choices])}


def test_bootstrap_ends_are_drawn_values_and_nest_by_level():
    a, b = np.array([1.0, 4.0, 9.0]), np.array([2.0, 3.0])
    statistic = lambda x, y: float(x.mean() - y.max())  # noqa: E731
    possible = _all_resample_values(statistic, [a, b])
    wide = bootstrap_interval(statistic, [a, b], level=0.9, draws=500, seed=3)
    narrow = bootstrap_interval(statistic, [a, b], level=0.5, draws=500, seed=3)
    assert set(wide) <= possible and set(narrow) <= possible
    assert wide[0] <= narrow[0] <= narrow[1] <= wide[1]
    assert min(possible) <= wide[0] < wide[1] <= max(possible)
    assert bootstrap_interval(statistic, [a, b], level=0.9, draws=500, seed=3) == wide  # same seed, same interval


def test_bootstrap_of_identical_runs_is_a_point_and_inf_is_an_end():
    runs = np.tile(np.array([[0.0, 2.0, 5.0]]), (4, 1))  # four seeds with the same curve
    assert bootstrap_interval(lambda r: float(r.mean(0)[-1]), [runs]) == (5.0, 5.0)
    # A statistic that is inf ("never reached") in most resamples: the upper end reads inf.
    low, high = bootstrap_interval(lambda x: np.inf if x.max() < 10 else 1.0, [np.array([0.0, 0.0, 0.0, 10.0])])
    assert (low, high) == (1.0, np.inf)


@pytest.mark.parametrize("kwargs", [dict(level=1.0), dict(level=0.0), dict(draws=0), dict(draws=True),
                                    dict(groups=[np.zeros(0)])])
def test_bootstrap_refuses_bad_arguments(kwargs):
    args = dict(statistic=lambda x: float(x.sum()), groups=[np.ones(3)]) | kwargs
    with pytest.raises(ValueError, match="bootstrap_interval"):
        bootstrap_interval(**args)
