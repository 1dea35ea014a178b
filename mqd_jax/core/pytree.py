"""Frozen dataclasses that are JAX pytrees: the states, params and results of the library.

`dataclass` is what `flax.struct.dataclass` gives (a frozen dataclass, registered with JAX, with `replace`),
without importing flax: `import mqd_jax` pays for flax only where a model is built or a checkpoint is written.
A field made with `field(pytree_node=False)` is static (part of the tree's structure, not a leaf). Every class
made here is listed in `CLASSES`, so that checkpoints (`mqd_jax.experiment.checkpoint`) can register them with
flax's serialization: each is saved as the dict of its pytree fields, as flax saves its own dataclasses.
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

import jax

T = TypeVar("T")
CLASSES: list[type] = []


def field(pytree_node: bool = True, **kwargs: Any) -> Any:
    """A dataclass field; `pytree_node=False` makes it static (not a leaf)."""
    return dataclasses.field(metadata={"pytree_node": pytree_node}, **kwargs)


def _replace(self: T, **changes: Any) -> T:
    return dataclasses.replace(self, **changes)


def dataclass(cls: type[T]) -> type[T]:
    """`cls` as a frozen dataclass registered as a JAX pytree (its pytree fields the leaves), with `replace`."""
    cls = dataclasses.dataclass(frozen=True)(cls)
    fields = dataclasses.fields(cls)
    data = [f.name for f in fields if f.metadata.get("pytree_node", True)]
    meta = [f.name for f in fields if not f.metadata.get("pytree_node", True)]
    jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)
    cls.replace = _replace
    CLASSES.append(cls)
    return cls
