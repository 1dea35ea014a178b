"""Work on a prefix: a search over the first `size` rows, for the smallest of a ladder of sizes that holds what
is needed (the skills fill a prefix of the repertoire's slots; a band or a run of cells is read `size` places
wide). Each size is a copy of the work in the program; one is chosen at run time (`batching.switch_largest`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import batching


def prefix(tree: Any, size: int, capacity: int) -> Any:
    """The per-slot arrays of `tree` cut to their first `size` slots."""
    return jax.tree.map(lambda x: x[:size] if x.ndim and x.shape[0] == capacity else x, tree)


def on_prefix(sizes: Sequence[int], needed: jax.Array, fn: Callable[..., Any], *operands: Any) -> Any:
    """fn(size, *operands) for the smallest of `sizes` (ascending) that is >= needed (capped at the last).

    `fn` must give the same result for every size >= needed; under vmap the
    batch then shares the size its largest member needs (`batching.switch_largest`).
    """
    index = jnp.searchsorted(jnp.asarray(sizes), jnp.minimum(needed, sizes[-1]))
    return batching.switch_largest(index, [functools.partial(fn, size) for size in sizes], *operands)


def prefix_sizes(capacity: int, min_prefix: int) -> list[int]:
    """The prefix sizes C / 2^j (at least `min_prefix`, at most C) that prefix work chooses from, ascending."""
    return sorted({max(capacity >> j, min(min_prefix, capacity)) for j in range(capacity.bit_length())})


def window_sizes(size: int, narrowest: int) -> list[int]:
    """The window lengths a search over `size` sorted rows chooses from, ascending: narrowest * 4^j up to half of
    size, and size (each length is a copy of the search in the program): `bands.MIN_WINDOW` for the skills' bands,
    `insertion.MIN_RUN` for the runs of the candidates' grid cells."""
    return [*(narrowest * 4**j for j in range(size.bit_length()) if 2 * narrowest * 4**j <= size), size]
