"""The shared checks of settings given as Python numbers."""

import math

import numpy as np
import pytest

from mqd_jax.core.checks import is_int, is_real


@pytest.mark.parametrize(("value", "expected"), [(3, True), (0, True), (-2, True), (True, False), (False, False),
                                                 (3.0, False), ("3", False), (None, False), (np.int32(3), False)])
def test_is_int_takes_ints_but_not_bools(value, expected):
    assert is_int(value) is expected


@pytest.mark.parametrize(("value", "expected"), [(3, True), (-0.5, True), (np.float64(0.25), True), (1e308, True),
                                                 (math.inf, False), (-math.inf, False), (math.nan, False),
                                                 (True, False), ("0.5", False), (None, False),
                                                 (np.float32(0.5), False)])
def test_is_real_takes_finite_numbers_only(value, expected):
    assert is_real(value) is expected
