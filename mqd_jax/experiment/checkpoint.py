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

from mqd_jax.core import diagnostics, pytree
from mqd_jax.core.checks import is_int
from mqd_jax.core.config import Config, check_params, upgraded
from mqd_jax.core.params import Params
from mqd_jax.core.run import State, check_state, get_task, init, kept_features, metric_dtypes, run_generations
from mqd_jax.experiment import folders
from mqd_jax.experiment.folders import differences, write_atomically
from mqd_jax.experiment.provenance import provenance

FORMAT = 10
# The parts of a model emitter's state that format 6 moved into its surrogate's (`SurrogateState`), and the gate
# format 7 added there (a fresh run's, where an older format's state is completed from one).
_SURROGATE = ("model", "rollouts", "anchor_errors", "validity", "gate")
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


def _from_format_1(state: dict[str, Any]) -> dict[str, Any]:
    """Format 1 saved the coverage grid's bounds as arrays; since format 2 they come from the config."""
    coverage = {k: v for k, v in state["coverage"].items() if k not in ("low", "high")}
    return {**state, "coverage": coverage}


def _from_format_3(state: dict[str, Any], fresh: dict[str, Any], cfg: Config) -> dict[str, Any]:
    """Formats 1-3 kept M-QD's model in `state["model"]` with Adam's state alone (QD and RANDOM an untrained
    one); since format 4 the model emitter's state holds it, Adam's state inside optax.inject_hyperparams'.
    `fresh`: the state dict of a new run of `cfg`, whose emitter state is filled in."""
    state = dict(state)
    old, emitter = state.pop("model"), fresh["emitter"]
    if "model" in emitter:
        model = emitter["model"]
        opt_state = model["opt_state"]
        opt_state["inner_state"]["0"] = old["opt_state"]
        opt_state["count"] = old["steps"]
        # The rate `train` last set, for a run with the config's own params.
        opt_state["hyperparams"]["learning_rate"] = np.full_like(opt_state["hyperparams"]["learning_rate"],
                                                                 cfg.emitter.surrogate.learning_rate)
        model.update(params=old["params"], steps=old["steps"])
        emitter["evaluations"] = state["num_evaluations"]
    return {**state, "emitter": emitter}


def _from_format_4(state: dict[str, Any], fresh: dict[str, Any], batched: bool) -> dict[str, Any]:
    """Format 4 held one network's parameters and Adam moments; since format 5 the model is an ensemble (a
    leading member axis, here of one member) and the model emitter's state also holds `rollouts` and
    `fallback` (empty for the one-network presets). `fresh`: the state dict of a new run of the config."""
    emitter = state["emitter"]
    if not (isinstance(emitter, dict) and "model" in emitter):
        return state
    member_axis = 1 if batched else 0  # after a batch's [S] axis
    grow = lambda tree: jax.tree.map(lambda x: np.expand_dims(np.asarray(x), member_axis), tree)  # noqa: E731
    model = dict(emitter["model"])
    adam = dict(model["opt_state"]["inner_state"]["0"])
    adam.update(mu=grow(adam["mu"]), nu=grow(adam["nu"]))
    inner_state = {**model["opt_state"]["inner_state"], "0": adam}
    model.update(params=grow(model["params"]), opt_state={**model["opt_state"], "inner_state": inner_state})
    return {**state, "emitter": {**fresh["emitter"], **emitter, "model": model}}


def _flat(emitter: Any) -> Any:
    """A model emitter's state dict of format 6 as formats 4-5 held it: the surrogate's parts beside the rest."""
    if not (isinstance(emitter, dict) and "surrogate" in emitter):
        return emitter
    return {**{k: v for k, v in emitter.items() if k != "surrogate"}, **emitter["surrogate"]}


def _from_format_5(state: dict[str, Any]) -> dict[str, Any]:
    """Formats 4-5 held the model, its rollout buffer, anchoring errors and validity classifier in the model
    emitter's state; since format 6 its surrogate's state (`SurrogateState`) holds them."""
    emitter = state["emitter"]
    if not (isinstance(emitter, dict) and "model" in emitter):
        return state
    surrogate = {k: emitter[k] for k in _SURROGATE if k in emitter}
    return {**state, "emitter": {**{k: v for k, v in emitter.items() if k not in _SURROGATE},
                                 "surrogate": surrogate}}


def _from_format_6(state: dict[str, Any]) -> dict[str, Any]:
    """Formats 1-6 had no gate (`mqd_jax.surrogate.gate`); since format 7 the surrogate's state holds one, empty
    for a surrogate without it."""
    emitter = state["emitter"]
    if not (isinstance(emitter, dict) and "surrogate" in emitter) or "gate" in emitter["surrogate"]:
        return state
    return {**state, "emitter": {**emitter, "surrogate": {**emitter["surrogate"], "gate": {}}}}


def _from_format_7(state: dict[str, Any], cfg: Config) -> dict[str, Any]:
    """Formats 1-7 kept no features per skill; since format 8 the repertoire keeps the task's features of each
    skill where the emitter asks (`Repertoire.features`): computed from the saved actions (0 in empty slots)."""
    rep = state["repertoire"]
    if "features" in rep:
        return state
    actions, valid = np.asarray(rep["actions"]), np.asarray(rep["valid"], bool)
    kept = kept_features(cfg)
    features = np.zeros((*actions.shape[:-1], kept), np.float32)
    if kept:
        computed = np.asarray(get_task(cfg).features(jnp.asarray(actions.reshape(-1, actions.shape[-1]))))
        features = np.where(valid[..., None], computed.reshape(features.shape), 0.0).astype(np.float32)
    return {**state, "repertoire": {**rep, "features": features}}


def _from_format_8(state: dict[str, Any]) -> dict[str, Any]:
    """Formats 6-8 held anchoring's averaged errors in the surrogate's state and no rule state; since format 9
    the model emitter holds both (`ModelEmitterState.anchor_errors`, `.acquisition`; the built-in rules keep
    none) and a step aside's state (empty: the configs of those formats have none)."""
    emitter = state["emitter"]
    if not (isinstance(emitter, dict) and "surrogate" in emitter):
        return state
    surrogate = dict(emitter["surrogate"])
    errors = surrogate.pop("anchor_errors", emitter.get("anchor_errors", {}))
    return {**state, "emitter": {**emitter, "surrogate": surrogate, "anchor_errors": errors,
                                 "acquisition": emitter.get("acquisition", {}),
                                 "step_aside": emitter.get("step_aside", {})}}


# Format 9's model emitter state fields that format 10 moved into its chain's parts' states, by part name.
_PARTS = {"fallback": "fallback", "steering": "steering", "step_aside": "step_aside", "anchor_errors": "anchoring"}


def _from_format_9(state: dict[str, Any]) -> dict[str, Any]:
    """Formats 1-9 held the model emitter's options' states as fields of its state; since format 10 its chain's
    parts hold theirs (`ModelEmitterState.parts`, by part name; a part not in the config's chain is not read)."""
    emitter = state["emitter"]
    if not (isinstance(emitter, dict) and "surrogate" in emitter):
        return state
    kept = {k: v for k, v in emitter.items() if k not in _PARTS}
    # A format 4 file's state was completed from a fresh run's (`_from_format_4`), whose parts it keeps.
    moved = {part: emitter[old] for old, part in _PARTS.items() if old in emitter}
    return {**state, "emitter": {**kept, "parts": {**moved, **emitter.get("parts", {})}}}


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


def read(path: str) -> dict[str, Any]:
    """The checkpoint's contents (config, key, state, metrics), checksum verified, its fields' types and shapes
    checked (`_check_fields`), older formats converted."""
    try:
        payload: Any = _restore(path, folders.read_bytes(path))
    except (OSError, folders.NotAFile) as e:
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
        payload["state"] = _from_format_1(payload["state"])
    return payload


def load(path: str, cfg: Config, key: jax.Array) -> tuple[State, Metrics]:
    """The state and metrics saved in `path` by a run of `cfg` started from `key`."""
    payload = read(path)
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
    differ = differences(upgraded(payload["config"]), cfg.to_dict())
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
        fresh = {**fresh, "emitter": _flat(fresh["emitter"])}  # as formats 4-5 held it
        if payload["format"] < 4:
            payload["state"] = _from_format_3(payload["state"], fresh, cfg)
        if payload["format"] < 5:
            payload["state"] = _from_format_4(payload["state"], fresh, key.ndim == 2)
        if payload["format"] < 6:
            payload["state"] = _from_format_5(payload["state"])
        payload["state"] = _from_format_9(_from_format_8(_from_format_7(_from_format_6(payload["state"]), cfg)))
    try:
        state = serialization.from_state_dict(template, payload["state"])
    except (KeyError, ValueError) as e:
        raise Refused(path, f"its state does not fit this config ({e})") from e
    for want, got in zip(jax.tree.leaves(template), jax.tree.leaves(state), strict=True):
        if want.shape != np.shape(got) or want.dtype != np.asarray(got).dtype:
            raise Refused(path, f"an array of shape {np.shape(got)} where {want.shape} was expected")
    state = jax.tree.map(lambda want, got: np.asarray(got, want.dtype), template, state)
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
    on_chunk: Callable[[State, Metrics], None] | None = None,
    on_start: Callable[[State, Metrics], None] | None = None,
    on_compiled: Callable[[], None] | None = None,
) -> tuple[State, Metrics]:
    """`run_mqd` in chunks of `every` generations, saving a checkpoint at `path` after each.

    With `resume` and a checkpoint at `path`, continues from it (it must come
    from the same config and key); the result is identical to an
    uninterrupted `run_mqd(key, cfg, params)`. `on_start(state, metrics)` is
    called before compiling with the state and metrics it starts from (empty
    unless resumed), `on_compiled()` once compiled, `on_chunk(state, metrics)`
    after each chunk with the chunk's metrics (for progress output). Warns
    like `run_mqd` at the end.
    """
    if not (is_int(every) and every >= 1):
        raise ValueError(f"every={every!r} is invalid: expected an int >= 1")
    params = cfg.params() if params is None else params
    check_params(params, cfg)
    if resume and folders.lexists(path):
        state, metrics = load(path, cfg, key)
    else:
        state, metrics = init(key, cfg), {}
    check_state(state, cfg)
    if on_start is not None:
        on_start(state, metrics)
    if int(state.generation) < cfg.max_generations:
        step = compile_chunk(state, cfg, params, every)
        if on_compiled is not None:
            on_compiled()
    while (done := int(state.generation)) < cfg.max_generations:
        todo = min(every, cfg.max_generations - done)
        state, chunk = step(state, params, todo)
        chunk = {k: np.asarray(v)[:todo] for k, v in chunk.items()}
        metrics = {k: np.concatenate([metrics[k], v]) if k in metrics else v for k, v in chunk.items()}
        save(path, state, metrics, cfg, key)
        if on_chunk is not None:
            on_chunk(state, chunk)
    diagnostics.warn(metrics, cfg, get_task(cfg))
    return state, metrics
