"""Checkpoints: a run's complete state and its metrics so far, in one file, and resumable runs.

A checkpoint is one msgpack file (`flax.serialization`): a format version, a
SHA-256 checksum and a body holding the run's config (every field), the key
the run started from, the whole `State` (repertoire, rejected archive, coverage
grid, the emitter's state (M-QD: model parameters and Adam state), key,
generation, evaluation count), the
per-generation metrics so far, the provenance (package versions, git
revision) and the task's `revision` (since 0.15; 0 before). `save` writes a
temporary file and renames it over the old one, so a crash leaves either the
previous checkpoint or the new one, never half of one.
`load` refuses, with a ValueError, a file that is not a checkpoint, is corrupt
or was altered (checksum), and one written for another config, task, task revision or key.
Files of the older formats 1 to 5 (1 and 2 without checksum; 1 to 3 with
M-QD's model outside the emitter's state; 1 to 4 with one network where the
model is now an ensemble; 1 to 5 with the model beside the emitter's other
parts where its surrogate now holds it; 1 to 6 without a gate; 1 to 7 without the features the repertoire
keeps per skill, computed from the saved actions; 1 to 8 with anchoring's errors in the surrogate's state
where the model emitter now holds them, and no acquisition rule's state; 1 to 9 with the model emitter's
options (fallback, steering, step aside, anchoring's errors) as fields of its state, where its chain's parts
now hold theirs) still load.

Keys must be raw uint32 keys (`jax.random.PRNGKey`), as everywhere in mqd-jax. A batch
of runs (`mqd_jax.experiment.sweep`) saves and loads the same way, with keys [S, 2] and
every state array carrying a leading [S] axis.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from mqd_jax.core import checks, diagnostics, pytree
from mqd_jax.core.checks import is_int
from mqd_jax.core.config import Config, check_params
from mqd_jax.core.params import Params
from mqd_jax.core.run import run_generations
from mqd_jax.core.state import METRICS, State, check_state, get_task, init, metric_dtypes
from mqd_jax.experiment import files, interrupts, migrations
from mqd_jax.experiment.folders import differences, write_atomically
from mqd_jax.experiment.provenance import provenance

FORMAT = 10
Metrics = dict[str, np.ndarray]


_REGISTERED: set[type] = set()


def _register_pytrees() -> None:
    """Registers mqd-jax's pytree dataclasses (`mqd_jax.core.pytree`) with flax's serialization as flax
    registers its own: each as the dict of its pytree fields (so the files are those flax dataclasses made)."""
    for cls in pytree.CLASSES:
        if cls in _REGISTERED:
            continue
        names = [f.name for f in dataclasses.fields(cls) if f.metadata.get("pytree_node", True)]

        def to_state_dict(x: Any, names: list[str] = names) -> dict[str, Any]:
            return {name: serialization.to_state_dict(getattr(x, name)) for name in names}

        def from_state_dict(x: Any, state: dict[str, Any], names: list[str] = names) -> Any:
            missing, unknown = set(names) - set(state), set(state) - set(names)
            if missing or unknown:
                raise ValueError(f"{type(x).__name__}: missing fields {sorted(missing)}, unknown fields "
                                 f"{sorted(unknown)}")
            return x.replace(**{name: serialization.from_state_dict(getattr(x, name), state[name], name=name)
                                for name in names})

        serialization.register_serialization_state(cls, to_state_dict, from_state_dict)
        _REGISTERED.add(cls)


def save(path: str, state: State, metrics: Metrics, cfg: Config, key: jax.Array, chunk: int | None = None) -> None:
    """Writes a checkpoint of `state` and `metrics` (each [generations]) atomically to `path`; `chunk`: the
    generations per compiled call of a batch (`sweep.run_batch`), which its resumption must keep to repeat it bit
    for bit (read back as the field "chunk")."""
    _register_pytrees()
    extra = {} if chunk is None else {"chunk": chunk}
    body = serialization.msgpack_serialize({
        **extra,
        "config": cfg.to_dict(),
        "key": np.asarray(key),
        "state": serialization.to_state_dict(jax.device_get(state)),
        "metrics": {k: np.asarray(v) for k, v in metrics.items()},
        "provenance": provenance(),
        "task_revision": get_task(cfg).revision,
    })
    payload = {"format": FORMAT, "sha256": hashlib.sha256(body).hexdigest(), "body": body}
    write_atomically(path, serialization.msgpack_serialize(payload))


class Refused(ValueError):
    """A checkpoint that cannot be used: damaged, altered, or of another config or key (`path`: the file)."""

    def __init__(self, path: str, why: str) -> None:
        super().__init__(f"checkpoint {path!r} refused: {why}")
        self.path = path



def _restore(path: str, data: bytes) -> Any:
    try:
        return serialization.msgpack_restore(data)
    except Exception as e:  # msgpack raises several types on damaged bytes
        raise Refused(path, f"not a readable checkpoint ({type(e).__name__}: {e})") from e


def _check_fields(path: str, payload: dict[str, Any]) -> None:
    """Refuses (`Refused`, naming the field) a checkpoint whose fields are missing or of another type or shape: its
    key [2] or [S, 2] uint32, its state with a generation per run, its metrics one row per generation done.

    The checksum guards against accidents, not a forger (who can compute a new one): these checks, and `load`'s
    against the config, are what a checkpoint's contents must satisfy."""
    for name, kind in (("config", dict), ("key", np.ndarray), ("state", dict), ("metrics", dict)):
        if name not in payload:
            raise Refused(path, f"it lacks the field {name!r} (not a whole checkpoint)")
        if not isinstance(payload[name], kind):
            raise Refused(path, f"its field {name!r} is a {type(payload[name]).__name__}, not a {kind.__name__}")
    key = payload["key"]
    if key.dtype != np.uint32 or key.ndim not in (1, 2) or key.shape[-1] != 2:
        raise Refused(path, f"its key is {key.dtype}{list(key.shape)}, not uint32 [2] or [S, 2]")
    generation = payload["state"].get("generation")
    generation = np.asarray(generation) if isinstance(generation, (np.ndarray, np.generic)) else None
    runs = () if key.ndim == 1 else key.shape[:1]
    if not (generation is not None and generation.dtype.kind in "iu" and generation.shape == runs):
        raise Refused(path, f"its state's generation is not an integer of shape {list(runs)}")
    if generation.size and (generation.min() != generation.max()):
        raise Refused(path, "its runs are at different generations")
    done = int(generation.max()) if generation.size else 0
    if done < 0:
        raise Refused(path, f"it is at generation {done}, which is negative")
    for name, value in payload["metrics"].items():
        if not (isinstance(value, np.ndarray) and value.shape == (*runs, done)):
            shape = list(np.shape(value)) if isinstance(value, np.ndarray) else type(value).__name__
            raise Refused(path, f"its metric {name!r} is {shape}, where its {done} generations done make "
                                f"{[*runs, done]}")


def _check_values(path: str, state: State, metrics: Metrics, cfg: Config) -> None:
    """Refuses (`Refused`, naming the field) a state or metrics that no run makes: a skill count outside 0 to the
    capacity or a valid mask that is not its prefix, a skill with a non-finite action, behavior or quality, a
    neighbour index outside the repertoire, a negative count (rollouts, archived skills, coverage balls), metrics
    of another dtype than a run's (float32, int32), a coverage outside [0, 1] or a negative count metric."""
    rep, capacity = state.repertoire, cfg.capacity
    count = np.asarray(rep.count)
    if ((count < 0) | (count > capacity)).any():
        wrong = count.min() if (count < 0).any() else count.max()
        raise Refused(path, f"its state's field 'repertoire.count' holds {wrong} skills, outside 0 to the capacity "
                            f"{capacity}")
    prefix = np.arange(capacity) < count[..., None]
    if not np.array_equal(np.asarray(rep.valid), prefix):
        raise Refused(path, "its state's field 'repertoire.valid' does not mark the first 'repertoire.count' "
                            "skills, as a repertoire's does")
    for name in ("actions", "behaviors", "qualities"):
        values = np.asarray(getattr(rep, name))
        finite = np.isfinite(values).reshape(*prefix.shape, -1).all(-1)
        if (prefix & ~finite).any():
            raise Refused(path, f"its state's field 'repertoire.{name}' holds a value that is not finite for a skill "
                                "(no run inserts one)")
    index = np.asarray(rep.neighbours.index)
    if ((index < -1) | (index >= capacity)).any():
        wrong = index.min() if (index < -1).any() else index.max()
        raise Refused(path, f"its state's field 'repertoire.neighbours.index' holds {wrong}, outside -1 (none) to "
                            f"{capacity - 1}")
    for name, value in (("num_evaluations", state.num_evaluations), ("archive.total", state.archive.total),
                        ("coverage.counts", state.coverage.counts)):
        if (np.asarray(value) < 0).any():
            raise Refused(path, f"its state's field {name!r} holds a negative count")
    for name, value in metrics.items():
        want = np.dtype(metric_dtypes(cfg)[name])
        if value.dtype != want:
            raise Refused(path, f"its metric {name!r} is {value.dtype}, where a run's is {want}")
        if name == "coverage" and not ((value >= 0) & (value <= 1)).all():
            raise Refused(path, "its metric 'coverage' holds a value outside [0, 1] (or NaN)")
        if name in METRICS and want.kind == "i" and (value < 0).any():
            raise Refused(path, f"its metric {name!r} holds a negative count")


def read(path: str) -> dict[str, Any]:
    """The checkpoint's contents (config, key, state, metrics), checksum verified, its fields' types and shapes
    checked (`_check_fields`), older formats converted."""
    try:
        payload: Any = _restore(path, files.read_bytes(path))
    except (OSError, files.NotAFile) as e:
        raise Refused(path, f"cannot read it ({e})") from e
    if not isinstance(payload, dict) or payload.get("format") not in range(1, FORMAT + 1):
        raise Refused(path, f"not an mqd-jax checkpoint of format 1 to {FORMAT}")
    if payload["format"] >= 3:
        body = payload.get("body")
        if not isinstance(body, bytes) or hashlib.sha256(body).hexdigest() != payload.get("sha256"):
            raise Refused(path, "its checksum does not match: the file was altered or damaged")
        body = _restore(path, body)
        if not isinstance(body, dict):
            raise Refused(path, "its body is not a dict of fields (not a whole checkpoint)")
        payload = {**body, "format": payload["format"]}
    _check_fields(path, payload)
    if payload["format"] == 1:
        payload["state"] = migrations.from_format_1(payload["state"])
    return payload


def load(path: str, cfg: Config, key: jax.Array, payload: dict[str, Any] | None = None) -> tuple[State, Metrics]:
    """The state and metrics saved in `path` by a run of `cfg` started from `key` (`payload`: what `read(path)`
    gave a caller that read it already, so that the file is read once)."""
    payload = read(path) if payload is None else payload
    done = int(np.asarray(payload["state"]["generation"]).reshape(-1)[0]) if payload["key"].size else 0
    if not 0 <= done <= cfg.max_generations:
        raise Refused(path, f"it is at generation {done}, outside 0 to {cfg.max_generations}, its run's length")
    metrics = payload["metrics"]
    unknown = sorted(set(metrics) - set(metric_dtypes(cfg)))
    if unknown or (done and "coverage" not in metrics):
        raise Refused(path, f"its metrics are not its config's ({', '.join(unknown) or 'none for its generations'})")
    counted = done and "num_evaluations" in metrics and "num_evaluations" in payload["state"]
    if counted and not np.array_equal(payload["state"]["num_evaluations"], metrics["num_evaluations"][..., -1]):
        raise Refused(path, "its state's rollouts do not match its metrics' count")
    differ = differences(migrations.upgraded(payload["config"]), cfg.to_dict())
    if differ:
        raise Refused(path, f"it was written with another config ({differ})")
    if not np.array_equal(payload["key"], np.asarray(key)):
        raise Refused(path, "it was written by a run started from another key")
    revision, now = payload.get("task_revision", 0), get_task(cfg).revision  # before 0.15: every task's 0
    if revision != now:
        raise Refused(path, f"it holds skills of revision {revision} of the task {cfg.task_name!r}, which is at "
                            f"revision {now} here (its rollouts give other outcomes: see CHANGELOG.md); run it "
                            "afresh, or resume it with the version of mqd-jax that wrote it")
    key = np.asarray(key)
    _register_pytrees()
    # Shapes only; a batch of runs (keys [S, 2]) saved its states with a leading [S] axis.
    start = (lambda k: init(k, cfg)) if key.ndim == 1 else jax.vmap(lambda k: init(k, cfg))
    template = jax.eval_shape(start, key)
    if payload["format"] < FORMAT:
        fresh = serialization.to_state_dict(jax.device_get(start(key)))
        payload["state"] = migrations.checkpoint_state(payload["state"], payload["format"], fresh, cfg,
                                                       key.ndim == 2)
    try:
        state = serialization.from_state_dict(template, payload["state"])
    except (KeyError, ValueError) as e:
        raise Refused(path, f"its state does not fit this config ({e})") from e
    for (where, want), got in zip(jax.tree_util.tree_flatten_with_path(template)[0], jax.tree.leaves(state),
                                  strict=True):
        got = np.asarray(got)
        if want.shape != got.shape or want.dtype != got.dtype:
            raise Refused(path, f"its state's field {jax.tree_util.keystr(where)[1:]!r} is {got.dtype}"
                                f"{list(got.shape)}, where this config's state has {want.dtype}{list(want.shape)}")
    state = jax.tree.map(lambda want, got: np.asarray(got, want.dtype), template, state)
    _check_values(path, state, payload["metrics"], cfg)
    metrics = dict(payload["metrics"])
    if metrics:  # metrics a later version added (0.12: max_quality, qd_score; 0.13: insertion_rounds): NaN (-1 for
        done = np.shape(metrics["coverage"])  # counts) for the generations before
        for name, dtype in metric_dtypes(cfg).items():
            if name not in metrics:
                floating = jnp.issubdtype(dtype, jnp.floating)
                metrics[name] = np.full(done, np.nan if floating else -1, np.float32 if floating else np.int32)
    return state, metrics


def compile_chunk(state: State, cfg: Config, params: Params, every: int) -> Callable[..., tuple[State, Metrics]]:
    """The compiled program of one chunk: `(state, params, todo) -> (state, metrics [every])`.

    One program of `min(every, cfg.max_generations)` generations, of which the
    first `todo` run, so a shorter last chunk needs no second compile. Compiled
    ahead of time, so the caller can time (or announce) the compilation.
    """
    length = min(every, cfg.max_generations)
    program = jax.jit(run_generations, static_argnums=(1, 3))
    compiled = program.lower(state, cfg, params, length, jnp.int32(length)).compile()
    return lambda s, p, todo: compiled(s, p, jnp.int32(todo))


def run_with_checkpoints(
    key: jax.Array,
    cfg: Config,
    path: str,
    every: int,
    params: Params | None = None,
    resume: bool = True,
    on_start: Callable[[State, Metrics], None] | None = None,
    progress: Any = None,
) -> tuple[State, Metrics]:
    """`run_mqd` in chunks of `every` generations, saving a checkpoint at `path` after each.

    With `resume` and a checkpoint at `path`, continues from it (it must come
    from the same config and key); the result is identical to an
    uninterrupted `run_mqd(key, cfg, params)`. `on_start(state, metrics)` is
    called before compiling with the state and metrics it starts from (empty
    unless resumed). `progress` (`mqd_jax.experiment.progress`: `Bar` for a bar, any `Progress` for a hook; None:
    nothing) is told where the run starts, the compilation and each chunk, after its checkpoint is saved. Warns
    like `run_mqd` at the end.
    """
    if not (is_int(every) and every >= 1):
        raise ValueError(f"every={every!r} is invalid: expected an int >= 1")
    params = cfg.params() if params is None else params
    check_params(params, cfg)
    if resume and files.lexists(path):
        state, metrics = load(path, cfg, key)
    else:
        state, metrics = init(key, cfg), {}
    check_state(state, cfg)
    if on_start is not None:
        on_start(state, metrics)
    if progress is not None:
        progress.resume(int(state.generation), metrics)

    def saved(state: State, metrics: Metrics, chunk: Metrics) -> None:
        save(path, state, metrics, cfg, key)

    return run_chunks(state, metrics, cfg, params, every, progress, saved)


def run_chunks(state: State, metrics: Metrics, cfg: Config, params: Params, every: int, progress: Any = None,
               after: Callable[[State, Metrics, Metrics], None] | None = None) -> tuple[State, Metrics]:
    """`state` (with its metrics so far) run on to `cfg.max_generations` in chunks of `every` generations, one
    compiled chunk (`compile_chunk`): after each, `after(state, the metrics so far, the chunk's)`, then
    `progress.chunk`, then a Ctrl-C pressed meanwhile is raised (`interrupts.check`, also after compiling);
    `progress` is told of the compilation and closed at the end. Warns like `run_mqd`."""
    if int(state.generation) < cfg.max_generations:
        if progress is not None:
            progress.compiling()
        step = compile_chunk(state, cfg, params, every)
        if progress is not None:
            progress.compiled()
    interrupts.check()
    while (done := int(state.generation)) < cfg.max_generations:
        todo = min(every, cfg.max_generations - done)
        with checks.part_failures():
            state, chunk = step(state, params, todo)
            chunk = {k: np.asarray(v)[:todo] for k, v in chunk.items()}
        metrics = {k: np.concatenate([metrics[k], v]) if k in metrics else v for k, v in chunk.items()}
        if after is not None:
            after(state, metrics, chunk)
        if progress is not None:
            progress.chunk(int(state.generation), chunk)
        interrupts.check()
    if progress is not None:
        progress.close()
    diagnostics.warn(metrics, cfg, get_task(cfg))
    return state, metrics
