"""`compiled(f)`: a library function called as one compiled program, as a run calls it.

Called eagerly, a function of JAX operations compiles a small program for each operation (hundreds for an
emitter's `propose`), which costs the suite far more than the one program a jit compiles. Tests that call a
library function directly call it through `compiled`: its array arguments are traced, every other argument (an
emitter, a task, a size, a Python function) is fixed, as the run fixes them. Calls with the same function and
fixed arguments share one program.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import numpy as np


def _is_array(x: Any) -> bool:
    return isinstance(x, jax.Array | np.ndarray | np.generic)


def _program(f: Callable[..., Any], tree: Any, fixed: tuple[Any, ...]) -> Callable[..., Any]:
    """The jitted `f` of the array leaves of its arguments; `fixed`: the other leaves (None where an array goes)."""
    def traced(arrays: list[jax.Array]) -> Any:
        given = iter(arrays)
        args, kwargs = jax.tree.unflatten(tree, [next(given) if x is _ARRAY else x for x in fixed])
        return f(*args, **kwargs)

    return jax.jit(traced)


_ARRAY = object()  # where an array leaf goes
_PROGRAMS: dict[Any, Callable[..., Any]] = {}  # (f, tree, each fixed leaf's type and value) -> its program


def compiled(f: Callable[..., Any]) -> Callable[..., Any]:
    """`f` jitted over the array leaves of its arguments; its other leaves are static (closed over)."""
    @functools.wraps(f)
    def call(*args: Any, **kwargs: Any) -> Any:
        leaves, tree = jax.tree.flatten((args, kwargs))
        fixed = tuple(_ARRAY if _is_array(x) else x for x in leaves)
        key = (f, tree, tuple((type(x), x) for x in fixed))  # typed: 1, 1.0 and True are different arguments
        try:
            program = _PROGRAMS.get(key) or _PROGRAMS.setdefault(key, _program(f, tree, fixed))
        except TypeError:  # an unhashable fixed argument: a program of this call alone
            program = _program(f, tree, fixed)
        return program([x for x in leaves if _is_array(x)])

    return call


def release() -> None:
    """Forgets the shared programs (conftest's `release_compiled_programs`, after each test module)."""
    _PROGRAMS.clear()
