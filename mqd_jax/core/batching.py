"""Control flow that batches well under `jax.vmap` (seed sweeps, threshold grids).

Plain vmap turns a `lax.cond` or `lax.switch` whose predicate differs between
members into a select that runs every branch for every member, and a
`while_loop` into one that, each step, selects between the new and the old
state of every member. The repertoire's insertion is made of such control
flow (its cost follows each member's repertoire size and changes), so it uses
these instead:

* `switch_largest(index, branches, *operands)`: branches that give the same
  result wherever they apply, a larger one applying more widely (the same work
  on a larger prefix of the repertoire); under vmap the batch takes the branch
  of its largest index, once.
* `rare_cond(pred, true_fn, false_fn, *operands)`: a cond whose `true_fn` is
  seldom needed; under vmap the batch runs it only when some member needs it.
* `for_each_chunk(mask, size, fn, carry, *operands)`: a loop over the set rows
  of a mask, `size` rows a step; under vmap the members step together until the
  last is done, and a member that is done steps on no rows, so no select.

Outside vmap they are exactly `lax.switch`, `lax.cond` and a `while_loop`.
`switch_largest` and `rare_cond` apply the same rule under nested vmaps (seeds
x hyperparameters); `for_each_chunk` does at the innermost level. The
functions passed in must not close over traced values: pass those as operands.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import jax
import jax.numpy as jnp

Carry = TypeVar("Carry")


def _broadcast(axis_size: int, in_batched: Sequence[Any], args: tuple[Any, ...]) -> tuple[Any, ...]:
    """`args` with a leading batch axis on every leaf (unbatched leaves repeated)."""
    return jax.tree.map(lambda x, batched: x if batched else jnp.broadcast_to(x, (axis_size, *jnp.shape(x))),
                        args, tuple(in_batched))


def _all_batched(tree: Any) -> Any:
    return jax.tree.map(lambda _: True, tree)


def switch_largest(index: jax.Array, branches: Sequence[Callable[..., Any]], *operands: Any) -> Any:
    """`lax.switch(index, branches, *operands)`; under vmap, every member takes the batch's largest index."""
    @jax.custom_batching.custom_vmap
    def switch(index: jax.Array, *operands: Any) -> Any:
        return jax.lax.switch(index, branches, *operands)

    @switch.def_vmap
    def rule(axis_size: int, in_batched: Sequence[Any], index: jax.Array, *operands: Any) -> tuple[Any, Any]:
        operands = _broadcast(axis_size, in_batched[1:], operands)
        out = switch_largest(index.max(), [jax.vmap(branch) for branch in branches], *operands)
        return out, _all_batched(out)

    return switch(index, *operands)


def rare_cond(pred: jax.Array, true_fn: Callable[..., Any], false_fn: Callable[..., Any], *operands: Any) -> Any:
    """`lax.cond(pred, true_fn, false_fn, *operands)`; under vmap, `true_fn` runs only if some member needs it."""
    @jax.custom_batching.custom_vmap
    def cond(pred: jax.Array, *operands: Any) -> Any:
        return jax.lax.cond(pred, true_fn, false_fn, *operands)

    @cond.def_vmap
    def rule(axis_size: int, in_batched: Sequence[Any], pred: jax.Array, *operands: Any) -> tuple[Any, Any]:
        pred, *operands = _broadcast(axis_size, in_batched, (pred, *operands))

        def some(pred: jax.Array, *operands: Any) -> Any:
            taken, other = jax.vmap(true_fn)(*operands), jax.vmap(false_fn)(*operands)
            return jax.tree.map(lambda t, f: jnp.where(pred.reshape((-1,) + (1,) * (t.ndim - 1)), t, f), taken, other)

        out = rare_cond(pred.any(), some, lambda _, *operands: jax.vmap(false_fn)(*operands), pred, *operands)
        return out, _all_batched(out)

    return cond(pred, *operands)


def _next_rows(todo: jax.Array, size: int) -> tuple[jax.Array, jax.Array]:
    """The first `size` set rows of todo[N] (N where there are fewer), and todo without them."""
    rows = jnp.nonzero(todo, size=size, fill_value=todo.shape[0])[0]
    return rows, todo.at[rows].set(False, mode="drop")


def for_each_chunk(mask: jax.Array, size: int, fn: Callable[..., Carry], carry: Carry, *operands: Any) -> Carry:
    """carry = fn(rows[size], carry, *operands) on the set rows of mask[N], `size` at a time; returns the carry.

    Unused places in `rows` hold N (out of range): gathers clamp, so `fn` must
    drop writes to them (`.at[rows].set(..., mode="drop")`); a step on no rows
    then leaves the carry as it is, which is what lets a batch step together.
    """
    def step(todo: jax.Array, carry: Carry, *operands: Any) -> tuple[jax.Array, Carry]:
        rows, todo = _next_rows(todo, size)
        return todo, fn(rows, carry, *operands)

    @jax.custom_batching.custom_vmap
    def loop(mask: jax.Array, carry: Carry, *operands: Any) -> Carry:
        return jax.lax.while_loop(lambda s: s[0].any(), lambda s: step(*s, *operands), (mask, carry))[1]

    @loop.def_vmap
    def rule(axis_size: int, in_batched: Sequence[Any], mask: jax.Array, carry: Carry, *operands: Any
             ) -> tuple[Carry, Any]:
        mask, carry, *operands = _broadcast(axis_size, in_batched, (mask, carry, *operands))
        steps = jax.vmap(step)
        out = jax.lax.while_loop(lambda s: s[0].any(), lambda s: steps(*s, *operands), (mask, carry))[1]
        return out, _all_batched(out)

    return loop(mask, carry, *operands)
