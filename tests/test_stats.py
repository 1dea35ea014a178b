import math

import numpy as np
import pytest

from mqd_jax.stats import mann_whitney


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
