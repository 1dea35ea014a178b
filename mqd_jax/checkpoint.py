"""Checkpoints: a run's complete state and its metrics so far, in one file, and resumable runs.

A checkpoint is one msgpack file (`flax.serialization`) holding a format
version, the run's config (every field), the key the run started from, the
whole `State` (repertoire, rejected archive, coverage grid, model parameters
and Adam state, key, generation, evaluation count) and the per-generation
metrics so far. `save` writes a temporary file and renames it over the old
one, so a crash leaves either the previous checkpoint or the new one, never
half of one. `load` refuses, with a ValueError, a file that is not a
checkpoint or is corrupt, and one written for another config, task or key.

Keys must be raw uint32 keys (`jax.random.PRNGKey`), as everywhere in mqd-jax. A batch
of runs (`mqd_jax.sweep`) saves and loads the same way, with keys [S, 2] and
every state array carrying a leading [S] axis.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from typing import Any

import jax
import numpy as np
from flax import serialization

from mqd_jax.config import Config, Params
from mqd_jax.run import State, init, run_generations

FORMAT = 2
Metrics = dict[str, np.ndarray]


def _from_format_1(state: dict[str, Any]) -> dict[str, Any]:
    """Format 1 saved the coverage grid's bounds as arrays; since format 2 they come from the config."""
    coverage = {k: v for k, v in state["coverage"].items() if k not in ("low", "high")}
    return {**state, "coverage": coverage}


def save(path: str, state: State, metrics: Metrics, cfg: Config, key: jax.Array) -> None:
    """Writes a checkpoint of `state` and `metrics` (each [generations]) atomically to `path`."""
    payload = {
        "format": FORMAT,
        "config": dataclasses.asdict(cfg),
        "key": np.asarray(key),
        "state": serialization.to_state_dict(jax.device_get(state)),
        "metrics": {k: np.asarray(v) for k, v in metrics.items()},
    }
    write_atomically(path, serialization.msgpack_serialize(payload))


def write_atomically(path: str, data: bytes) -> None:
    """Writes `data` to a temporary file and renames it over `path`: a crash leaves the old file or the new one."""
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _refuse(path: str, why: str) -> ValueError:
    return ValueError(f"checkpoint {path!r} refused: {why}")


def load(path: str, cfg: Config, key: jax.Array) -> tuple[State, Metrics]:
    """The state and metrics saved in `path` by a run of `cfg` started from `key`."""
    with open(path, "rb") as f:
        data = f.read()
    try:
        payload: Any = serialization.msgpack_restore(data)
    except Exception as e:  # msgpack raises several types on damaged bytes
        raise _refuse(path, f"not a readable checkpoint ({type(e).__name__}: {e})") from e
    if not isinstance(payload, dict) or payload.get("format") not in (1, FORMAT):
        raise _refuse(path, f"not an mqd-jax checkpoint of format 1 or {FORMAT}")
    if payload["format"] == 1:
        payload["state"] = _from_format_1(payload["state"])
    saved = payload["config"]
    differ = {k: (saved.get(k), v) for k, v in dataclasses.asdict(cfg).items() if saved.get(k) != v}
    if differ:
        listed = ", ".join(f"{k}: saved {a!r}, now {b!r}" for k, (a, b) in sorted(differ.items()))
        raise _refuse(path, f"it was written with another config ({listed})")
    if not np.array_equal(payload["key"], np.asarray(key)):
        raise _refuse(path, "it was written by a run started from another key")
    key = np.asarray(key)
    # Shapes only; a batch of runs (keys [S, 2]) saved its states with a leading [S] axis.
    start = (lambda k: init(k, cfg)) if key.ndim == 1 else jax.vmap(lambda k: init(k, cfg))
    template = jax.eval_shape(start, key)
    try:
        state = serialization.from_state_dict(template, payload["state"])
    except (KeyError, ValueError) as e:
        raise _refuse(path, f"its state does not fit this config ({e})") from e
    for want, got in zip(jax.tree.leaves(template), jax.tree.leaves(state), strict=True):
        if want.shape != np.shape(got) or want.dtype != np.asarray(got).dtype:
            raise _refuse(path, f"an array of shape {np.shape(got)} where {want.shape} was expected")
    state = jax.tree.map(lambda want, got: np.asarray(got, want.dtype), template, state)
    return state, dict(payload["metrics"])


def run_with_checkpoints(
    key: jax.Array,
    cfg: Config,
    path: str,
    every: int,
    params: Params | None = None,
    resume: bool = True,
    on_chunk: Callable[[State, Metrics], None] | None = None,
) -> tuple[State, Metrics]:
    """`run_mqd` in chunks of `every` generations, saving a checkpoint at `path` after each.

    With `resume` and a checkpoint at `path`, continues from it (it must come
    from the same config and key); the result is identical to an
    uninterrupted `run_mqd(key, cfg, params)`. `on_chunk(state, metrics)` is
    called after each chunk with the chunk's metrics (for progress output).
    """
    if not (isinstance(every, int) and every >= 1):
        raise ValueError(f"every={every!r} is invalid: expected an int >= 1")
    params = cfg.params() if params is None else params
    if resume and os.path.exists(path):
        state, metrics = load(path, cfg, key)
    else:
        state, metrics = init(key, cfg), {}
    step = jax.jit(run_generations, static_argnums=(1, 3))
    while (done := int(state.generation)) < cfg.max_generations:
        state, chunk = step(state, cfg, params, min(every, cfg.max_generations - done))
        chunk = jax.tree.map(np.asarray, chunk)
        metrics = {k: np.concatenate([metrics[k], v]) if k in metrics else v for k, v in chunk.items()}
        save(path, state, metrics, cfg, key)
        if on_chunk is not None:
            on_chunk(state, chunk)
    return state, metrics
