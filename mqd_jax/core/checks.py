"""What a setting given as a Python number must be: the checks every part's constructor shares.

A leaf module (it imports nothing of the package), so that `config` and the
parts it builds (emitters, rules, steering, pursuit) use the same ones, for
static settings (`is_int`, `is_real`) and traced parameters (`check_traced`).
"""

from __future__ import annotations

import contextlib
import math
import re
from collections.abc import Iterator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def is_int(value: Any) -> bool:
    """An int, not a bool (True is an int to Python, but never a count or a size here)."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_real(value: Any) -> bool:
    """A finite int or float, not a bool: NaN and +-inf are refused (no setting here means anything at them)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_traced(owner: str, name: str, value: Any, lowest: float = 0.0, inclusive: bool = True,
                 highest: float | None = None) -> None:
    """Raises ValueError naming `owner.name` unless every element of a concrete traced parameter is finite and
    >= `lowest` (> `lowest` unless `inclusive`; -inf: any finite) and <= `highest` (if given).

    Traced values (inside a user's `jit` or `vmap`) cannot be read and are not checked. Batched values (a sweep's
    [R]) are checked element by element; the message gives the first bad one.
    """
    if isinstance(value, jax.core.Tracer):
        return
    v = np.asarray(value, np.float64)
    bad = ~np.isfinite(v) | ((v < lowest) if inclusive else (v <= lowest))
    if highest is not None:
        bad |= v > np.float32(highest)
    if bad.any():
        relation = ">=" if inclusive else ">"
        allowed = "any finite float" if lowest == -math.inf else f"a finite float {relation} {lowest:g}"
        if highest is not None:
            allowed += f" and <= {highest}"
        raise ValueError(f"{owner}.{name}={float(v.ravel()[np.argmax(bad.ravel())])!r} is invalid: expected {allowed}")


def shapes_of(tree: Any) -> str:
    """A pytree's leaves as dtype[shape] (what a contract's message shows of what a part returned)."""
    leaves = jax.tree.leaves(tree)
    text = ", ".join(f"{jnp.result_type(x).name}{list(jnp.shape(x))}" for x in leaves)
    return f"({text})" if len(leaves) != 1 else text


class PartFailed(ValueError):
    """A part broke its contract while the program ran (`ModelEmitter(checks=True)`): raised in a host callback,
    and by the runners again as itself, one line (`part_failures`), not as the runtime's error that carries it."""


_CARRIED = re.compile(r"PartFailed: (.+)$", flags=re.M)


@contextlib.contextmanager
def part_failures() -> Iterator[None]:
    """Around what waits for a run's results: a `PartFailed` raised in the program's host callback is raised as
    itself (its one line), instead of the runtime error whose message carries its traceback."""
    try:
        yield
    except jax.errors.JaxRuntimeError as error:
        carried = _CARRIED.findall(str(error))
        if not carried:
            raise
        raise PartFailed(carried[-1]) from None
