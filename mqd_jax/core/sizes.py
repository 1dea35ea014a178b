"""What a run's arrays need, known before anything runs, and the check that refuses a run they cannot fit.

A run holds its state (the repertoire, archive, coverage and the emitter's
state: exact, from their shapes) and, in each generation, distance matrices
between the candidates and the skills: the population against the repertoire,
the archive and itself (novelty, insertion), and an emitter's pool (a model's
candidates) against the repertoire and archive. Those matrices are about
`PAIR_BYTES` bytes per pair (measured: population 100 x capacity 10^8 asked
XLA for 85 GB; population 10^6 x capacity 10^6 for 12 TB). A run that would
need more than the device's memory is refused before it is traced or compiled,
with the bytes it would need; the estimate is rough for the temporaries, so a
run near the limit may still fail when it allocates.
"""

from __future__ import annotations

import math
import os
from typing import Any

import jax

PAIR_BYTES = 12  # a generation's candidate x skill distance matrices: about three float32 arrays per pair


def tree_bytes(shapes: Any) -> int:
    """The bytes of a pytree of arrays or `jax.ShapeDtypeStruct`s."""
    return sum(math.prod(x.shape) * x.dtype.itemsize for x in jax.tree.leaves(shapes))


def generation_bytes(population: int, pool: int, capacity: int, archive_capacity: int) -> int:
    """The bytes of a generation's distance matrices (see the module's docstring)."""
    slots = capacity + archive_capacity
    return PAIR_BYTES * (population * (slots + population) + (pool - population) * slots)


def device_bytes(device: jax.Device | None = None) -> int | None:
    """The memory of `device` (default: the first), or None where it cannot be known: an accelerator's limit
    (`memory_stats`), a CPU's physical memory."""
    device = device or jax.local_devices()[0]
    try:
        stats = device.memory_stats()
    except Exception:  # a backend without memory statistics
        stats = None
    if stats and stats.get("bytes_limit"):
        return int(stats["bytes_limit"])
    if device.platform == "cpu":
        try:
            return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):
            return None
    return None


def gigabytes(n: int) -> str:
    """`n` bytes in words: '12.1 GB', '24,000 GB', '10.5 MB'."""
    return f"{n / 1e9:,.1f} GB" if n >= 1e8 else f"{n / 1e6:.1f} MB"


def check(state: Any, population: int, pool: int, capacity: int, archive_capacity: int, runs: int = 1,
          available: int | None = None) -> int:
    """Raises ValueError, with the bytes needed, if `runs` runs (a vmapped batch) of a state of shapes `state` and
    generations of `population` candidates (an emitter's `pool` of them judged) cannot fit in `available` bytes
    (default: the device's memory); returns the bytes needed."""
    held = tree_bytes(state) * runs
    temporary = generation_bytes(population, pool, capacity, archive_capacity) * runs
    available = device_bytes() if available is None else available
    if available is not None and held + temporary > available:
        batch = f"{runs} runs" if runs > 1 else "a run"
        raise ValueError(f"{batch} of population_size {population} and capacity {capacity} would need about "
                         f"{gigabytes(held + temporary)} ({gigabytes(held)} of state, {gigabytes(temporary)} of a "
                         f"generation's distances between candidates and skills), more than the device's "
                         f"{gigabytes(available)}: lower capacity, archive_capacity or population_size")
    return held + temporary
