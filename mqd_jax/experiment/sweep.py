"""Sweeps: many runs of one config (seeds, or a grid of traced `Params`) as one compiled, vmapped call.

`run_batch(cfg, keys, params)` runs R = len(keys) runs of `cfg` side by side
(`jax.vmap` of `init` and `run_generations`), in chunks of generations so that
a long sweep reports progress. The run axis is laid out over a `Mesh` of
every device `jax.devices()` lists (padded to a multiple of the device count
with copies of the last run, which are dropped again), so the same call runs
on one CPU or spreads its runs over eight GPUs. On several hosts, call
`jax.distributed.initialize()` in every process first: `jax.devices()` then
lists all hosts' devices, inputs are built with
`jax.make_array_from_callback` and the results are gathered to every process
(tested with two local processes on a CPU coordinator: both gather exactly the
metrics of one process with two devices).

Batched runs are reproducible (same keys, config and chunk size give the same
result on a backend) but are not bit-identical to the same runs made one at a
time: a vmapped program rounds some operations differently, and QD's runs
diverge after tens of generations. They agree in distribution.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from mqd_jax.core import checks, diagnostics
from mqd_jax.core.checks import is_int
from mqd_jax.core.config import Config, check_params
from mqd_jax.core.params import Params
from mqd_jax.core.run import run_generations
from mqd_jax.core.state import State, check_size, get_task, init
from mqd_jax.experiment import interrupts

Metrics = dict[str, np.ndarray]


def seed_keys(seeds: int, key: jax.Array | None = None) -> jax.Array:
    """[seeds, 2] the keys of a seed sweep: `seeds` splits of `key` (default PRNGKey(0))."""
    if not (is_int(seeds) and seeds >= 1):
        raise ValueError(f"seeds={seeds!r} is invalid: expected an int >= 1")
    return jax.random.split(jax.random.PRNGKey(0) if key is None else key, seeds)


def param_names(params: Params) -> list[str]:
    """The dotted names of the leaves of `params` ("t_dist", "emitter.acquisition.t_nov", ...), what `grid` takes."""
    return [jax.tree_util.keystr(path)[1:] for path, _ in jax.tree_util.tree_flatten_with_path(params)[0]]


def grid(cfg: Config, values: Mapping[str, Sequence[float]],
         seeds: int) -> tuple[jax.Array, Params, list[tuple[float, ...]]]:
    """Keys [P*S, 2] and batched Params [P*S] for every combination of `values` and seed (combination-major),
    and the P combinations.

    `values` maps a traced parameter's dotted name (`param_names(cfg.params())`, e.g. the paper's thresholds
    "emitter.acquisition.t_nov" and "emitter.acquisition.t_qua" of "mqd-paper") to the values it takes; the
    others keep the config's. Every combination uses the same S seed keys, so settings are compared on the same
    seeds. Raises ValueError for an unknown name, an empty list, or a value the parameter's owner refuses.
    """
    base = cfg.params()
    names = param_names(base)
    unknown = [name for name in values if name not in names]
    if unknown:
        raise ValueError(f"grid: {cfg.algorithm_name} has no traced parameter {unknown[0]!r}; its parameters: "
                         f"{', '.join(names)}")
    combos = list(itertools.product(*values.values()))
    if not combos:
        raise ValueError("the grid is empty: give at least one value of every parameter")
    leaves, structure = jax.tree.flatten(base)
    columns = []
    for name, leaf in zip(names, leaves, strict=True):
        at = list(values).index(name) if name in values else None
        column = [np.float32(leaf) if at is None else np.float32(combo[at]) for combo in combos]
        columns.append(jnp.repeat(jnp.asarray(column, jnp.float32), seeds))
    params = jax.tree.unflatten(structure, columns)
    check_params(params, cfg)
    return jnp.tile(seed_keys(seeds), (len(combos), 1)), params, combos


def _shard(x: np.ndarray, sharding: NamedSharding) -> jax.Array:
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])


def _gather(x: jax.Array) -> np.ndarray:
    return np.asarray(multihost_utils.process_allgather(x, tiled=True) if jax.process_count() > 1 else x)


@functools.partial(jax.jit, static_argnames=("cfg",))
def _init(keys: jax.Array, cfg: Config) -> State:
    return jax.vmap(lambda k: init(k, cfg))(keys)


@functools.partial(jax.jit, static_argnames=("cfg", "num"), donate_argnums=0)
def _chunk(states: State, params: Params, todo: jax.Array, cfg: Config, num: int) -> tuple[State, dict[str, jax.Array]]:
    """`num` generations of every run, of which the first `todo` run (one program for every chunk)."""
    return jax.vmap(lambda s, p: run_generations(s, cfg, p, num, todo))(states, params)


def run_batch(
    cfg: Config,
    keys: jax.Array,
    params: Params | None = None,
    chunk: int | None = None,
    start: tuple[State, Metrics] | None = None,
    on_state: Callable[[State, Metrics], None] | None = None,
    progress: Any = None,
) -> tuple[State, Metrics]:
    """R runs of `cfg`, vmapped and sharded over the devices.

    Args:
      cfg: static configuration, shared by every run.
      keys: [R, 2] one key per run (`seed_keys`).
      params: traced parameters: unbatched (every run uses them; default
        `cfg.params()`) or with a leading axis [R] (`grid`).
      chunk: generations per compiled call (default: the whole run; its program is compiled ahead of the first
        chunk, once for every chunk).
      start: (states [R], metrics [R, done]) of these runs after `done`
        generations, as `on_state` gave them: the batch continues from there
        and, with the same chunk, ends bit for bit as it would have without the
        stop (`mqd sweep` resumes an interrupted batch so).
      on_state: called after each chunk, before `progress.chunk`, with the states
        (numpy, leading [R]) and every metric so far ([R, done]): what a
        checkpoint of the batch holds.
      progress: told where the batch starts, of the compilation and of each chunk (generations done, that
        chunk's metrics, each [R, chunk]) (`mqd_jax.experiment.progress`: `Bar` for a bar, any `Progress` for a
        hook; None: nothing). A Ctrl-C pressed inside `interrupts.latched` stops the batch after the compilation or
        the chunk it came in (`interrupts.check`).

    Returns:
      The final states (every array with a leading [R] axis, on the devices)
      and the per-generation metrics, each a numpy array [R, max_generations].

    Raises ValueError for bad keys, params (shapes; NaN, infinite or out-of-range
    values) or chunk; warns like `run_mqd` (`diagnostics.RunWarning`) at the end.
    """
    keys = np.asarray(keys)
    if keys.ndim != 2 or keys.shape[1] != 2 or keys.dtype != np.uint32:
        raise ValueError(f"keys must be raw uint32 keys of shape (R, 2) (see seed_keys); got {keys.dtype}{keys.shape}")
    runs = keys.shape[0]
    params = cfg.params() if params is None else params
    shapes = {np.shape(leaf) for leaf in jax.tree.leaves(params)}
    if shapes == {()}:
        params = jax.tree.map(lambda x: jnp.broadcast_to(x, (runs,)), params)
    elif shapes != {(runs,)}:
        raise ValueError(f"params must be scalars or have shape ({runs},) (one per key); got shapes {sorted(shapes)}")
    check_params(params, cfg)
    chunk = cfg.max_generations if chunk is None else chunk
    if not (is_int(chunk) and chunk >= 1):
        raise ValueError(f"chunk={chunk!r} is invalid: expected an int >= 1")
    chunk = min(chunk, cfg.max_generations)
    check_size(cfg, -(-runs // jax.device_count()))  # each device holds its share of the runs

    devices = jax.devices()
    padded = -(-runs // len(devices)) * len(devices)
    pad = lambda x: np.concatenate([x, np.repeat(x[-1:], padded - runs, 0)])  # noqa: E731
    sharding = NamedSharding(Mesh(np.array(devices), ("runs",)), PartitionSpec("runs"))
    if start is None:
        states, parts = _init(_shard(pad(keys), sharding), cfg), []
    else:
        states = jax.tree.map(lambda x: _shard(pad(np.asarray(x)), sharding), start[0])
        parts = [dict(start[1])] if start[1] else []
    params = jax.tree.map(lambda x: _shard(pad(np.asarray(x, np.float32)), sharding), params)
    if progress is not None:
        progress.resume(sum(p["coverage"].shape[1] for p in parts), parts[0] if parts else {})
        progress.compiling()
    step = _chunk.lower(states, params, jnp.int32(chunk), cfg, chunk).compile()
    if progress is not None:
        progress.compiled()
    interrupts.check()
    while (done := sum(p["coverage"].shape[1] for p in parts)) < cfg.max_generations:
        todo = min(chunk, cfg.max_generations - done)
        with checks.part_failures():
            states, metrics = step(states, params, jnp.int32(todo))
            parts.append({k: _gather(v)[:runs, :todo] for k, v in metrics.items()})
        if on_state is not None:
            on_state(jax.tree.map(lambda x: _gather(x)[:runs], states),
                     {k: np.concatenate([p[k] for p in parts], axis=1) for k in parts[-1]})
        if progress is not None:
            progress.chunk(done + todo, parts[-1])
        interrupts.check()
    if progress is not None:
        progress.close()
    states = jax.tree.map(lambda x: x[:runs], states)
    metrics = {k: np.concatenate([p[k] for p in parts], axis=1) for k in parts[0]}
    diagnostics.warn(metrics, cfg, get_task(cfg))
    return states, metrics
