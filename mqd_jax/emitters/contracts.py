"""A model emitter's parts checked against their contracts, each failure one line naming the part.

Shapes and dtypes are checked as the program is traced, at no cost to the run (a surrogate's: in
`mqd_jax.surrogate.protocol.Hooks`; a rule's `select`: `selection`). Values (rows out of range or repeated,
predictions not finite) can only be seen while the program runs: `ModelEmitter(checks=True)` checks them every
generation (`values`), raising through a host callback where one fails, which costs a round trip only then;
the tests run with it, and a user trying a new part should too.
"""

from __future__ import annotations

import logging
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core.checks import PartFailed
from mqd_jax.core.checks import shapes_of as _shapes


def selection(rule: Any, out: Any, num: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """A rule's `select` output `out`, checked to be (rows int[num], rollout bool[num], discarded int scalar):
    ValueError naming the rule otherwise."""
    fine = isinstance(out, tuple | list) and len(out) == 3
    if fine:
        rows, rollout, discarded = out
        fine = (jnp.shape(rows) == (num,) and jnp.issubdtype(jnp.result_type(rows), jnp.integer)
                and jnp.shape(rollout) == (num,) and jnp.result_type(rollout) == jnp.bool_
                and jnp.shape(discarded) == () and jnp.issubdtype(jnp.result_type(discarded), jnp.integer))
    if not fine:
        raise ValueError(f"{type(rule).__name__}.select returned {_shapes(out)}; expected the rows int[{num}] it "
                         f"keeps, their rollout mask bool[{num}] and the int count it turned down")
    return out


def values(rule: Any, surrogate: Any, rows: jax.Array, pool_size: int, predictions: jax.Array,
           warm_up: jax.Array) -> None:
    """While the program runs: the rule's rows in [0, pool_size) and distinct, and (after warm-up) the
    surrogate's predictions [E, N, d + 1] finite; else a ValueError naming the part, raised through a host
    callback (the run stops with it)."""
    in_range = (rows >= 0) & (rows < pool_size)
    counts = jnp.zeros(pool_size, jnp.int32).at[jnp.where(in_range, rows, pool_size)].add(1, mode="drop")
    name = type(rule).__name__
    _fail_if(~in_range.all(), f"{name}.select returned rows outside the pool's [0, {pool_size})")
    _fail_if(counts.max() > 1, f"{name}.select returned a row more than once: its rows must be distinct")
    _fail_if(~warm_up & ~jnp.isfinite(predictions).all(),
             f"{type(surrogate).__name__} predicted values that are not finite (NaN or inf) after warm-up")


class _Quiet(logging.Filter):
    """Keeps JAX from logging a part's failure with its traceback: the runners raise it as one line."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not (record.exc_info and isinstance(record.exc_info[1], PartFailed))


logging.getLogger("jax._src.debugging").addFilter(_Quiet())


def _fail_if(bad: jax.Array, message: str) -> None:
    def fail(seen: Any) -> None:
        if np.any(seen):  # under vmap the cond is a select: the callback runs every generation, told whether bad
            raise PartFailed(message)

    jax.lax.cond(bad, lambda: jax.debug.callback(fail, bad), lambda: None)
