"""What a setting given as a Python number must be: the checks every part's constructor shares.

A leaf module (it imports nothing of the package), so that `config` and the
parts it builds (emitters, rules, steering, pursuit) use the same ones.
"""

from __future__ import annotations

import math
from typing import Any


def is_int(value: Any) -> bool:
    """An int, not a bool (True is an int to Python, but never a count or a size here)."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_real(value: Any) -> bool:
    """A finite int or float, not a bool: NaN and +-inf are refused (no setting here means anything at them)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
