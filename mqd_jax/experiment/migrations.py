"""What files of earlier versions hold, in today's form: saved configs (`upgraded`, `config_from`) and
checkpoints' states (`checkpoint_state`, format by format). `mqd_jax.experiment.checkpoint`, `results` and the
command line read every saved config and checkpoint through here; `Config.from_dict` reads today's form only.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import algorithms
from mqd_jax.core.config import Config
from mqd_jax.core.state import get_task, kept_features


def config_from(saved: dict[str, Any]) -> Config:
    """The config a file of any version saved (`Config.from_dict` of `upgraded(saved)`)."""
    return Config.from_dict(upgraded(saved))


# The fields a config had before version 0.10 put a preset's settings into `algorithm_options`.
_FLAT = ("t_nov", "t_qua", "learning_rate", "batch_size", "num_batches", "warmup_samples", "hidden_size",
         "iso_sigma", "line_sigma", "pool_factor", "ensemble_size", "optimism", "steering_share", "anchor",
         "parent_weight", "quality_share", "wide_scale", "budgeted")
# Adaptation's settings, arguments of `mqd_jax.adapt` since version 0.10.
_ADAPTATION = ("adaptation_step_size", "adaptation_steps")


def _flat_defaults() -> dict[str, Any]:
    """Today's defaults of the flat fields, for configs saved before a field existed."""
    return {**algorithms.options("mqd"), **algorithms.options("mqd-paper")}


def upgraded(saved: dict[str, Any]) -> dict[str, Any]:
    """A config dict saved by an earlier version in today's fields. Before version 0.10 a preset's settings were
    fields of the config: they become its `algorithm_options` (those the preset takes), and adaptation's two
    (arguments of `adapt` now) are dropped. Before that: `physics_backend` "auto" is dropped (since
    version 0.2 a robot task's backend is an option of its construction, `task_options`); before version 0.3
    (configs without `ensemble_size`) "mqd" was the paper's filter, today's "mqd-paper", and `pool_factor`
    defaulted to 4; before version 0.5 (configs without `steering_share`) "mqd" did not steer; before version
    0.6 (configs without `anchor`) it anchored at the nearest skill; before version 0.7 (configs without
    `parent_weight`) it ranked predicted openers by their distance alone; before version 0.8 (configs without
    `quality_share`) it made no quality steps; before version 0.9 (configs without `wide_scale`) it varied its
    pool at one scale; before version 0.11 (options without `features`) "mqd"'s model took neither the task's
    features nor a gate."""
    saved = dict(saved)
    if "algorithm_options" in saved:  # version 0.10 or later
        return _since_0_10(saved)
    defaults = _flat_defaults()
    if "ensemble_size" not in saved:
        saved.setdefault("pool_factor", 4)
        if saved.get("algorithm") == "mqd":
            saved["algorithm"] = "mqd-paper"
        for name in ("ensemble_size", "optimism"):  # fields that did not exist: today's defaults
            saved[name] = defaults[name]
    if "steering_share" not in saved:  # before version 0.5 "mqd" did not steer
        saved["steering_share"] = 0.0 if saved.get("algorithm") == "mqd" else defaults["steering_share"]
    if "anchor" not in saved:  # before version 0.6 "mqd" anchored at the nearest skill
        saved["anchor"] = "nearest" if saved.get("algorithm") == "mqd" else defaults["anchor"]
    if "parent_weight" not in saved:  # before version 0.7 "mqd" ranked by the predicted distance alone
        saved["parent_weight"] = 0.0 if saved.get("algorithm") == "mqd" else defaults["parent_weight"]
    if "quality_share" not in saved:  # before version 0.8 "mqd" made no quality steps
        saved["quality_share"] = 0.0 if saved.get("algorithm") == "mqd" else defaults["quality_share"]
    if "wide_scale" not in saved:  # before version 0.9 "mqd" varied its pool at one scale
        saved["wide_scale"] = 1.0 if saved.get("algorithm") == "mqd" else defaults["wide_scale"]
    backend = saved.pop("physics_backend", "auto")
    if backend != "auto":
        saved["task_options"] = {**saved.get("task_options", {}), "backend": backend}
    flat = {name: saved.pop(name) for name in _FLAT if name in saved}  # before version 0.10: fields of the config
    for name in _ADAPTATION:
        saved.pop(name, None)
    taken = algorithms.options(saved["algorithm"]) if saved.get("algorithm") in algorithms.names() else {}
    saved["algorithm_options"] = {name: value for name, value in flat.items() if name in taken}
    return _since_0_10(saved)


def _since_0_10(saved: dict[str, Any]) -> dict[str, Any]:
    """A config dict of version 0.10 or later in today's options: "mqd" without `features` (before version 0.11)
    took neither the task's features nor a gate; without `validity` (before version 0.16) it had neither a
    validity classifier nor a step aside, and trained on the repertoire; a config without `coverage_samples`
    (before version 0.12, when every behavior space had two dimensions and a coverage grid) takes today's
    default, which a grid does not read; "mqd" and "mqd-local" without `curiosity` (before version 0.23) had no
    `Curiosity` (its default, 0); "mqd" without `opener_cap` (before version 0.23.3) no cap (its default, 0);
    without `novelty_sampling` (before version 0.23.4) uniform mini-batches (its default, 0)."""
    options = dict(saved.get("algorithm_options", {}))
    if saved.get("algorithm") == "mqd" and "features" not in options:
        options.update(features=False, gate=False)
    if saved.get("algorithm") == "mqd" and "validity" not in options:
        options.update(validity=False, step_aside=False, training_data="repertoire", rollout_buffer=4096)
    if saved.get("algorithm") in ("mqd", "mqd-local") and "curiosity" not in options:
        options.update(curiosity=0.0)
    if saved.get("algorithm") == "mqd" and "opener_cap" not in options:
        options.update(opener_cap=0.0)
    if saved.get("algorithm") == "mqd" and "novelty_sampling" not in options:
        options.update(novelty_sampling=0.0)
    return {"coverage_samples": Config.coverage_samples, **saved, "algorithm_options": options}


# The parts of a model emitter's state that format 6 moved into its surrogate's (`SurrogateState`), and the gate
# format 7 added there (a fresh run's, where an older format's state is completed from one).
_SURROGATE = ("model", "rollouts", "anchor_errors", "validity", "gate")


def from_format_1(state: dict[str, Any]) -> dict[str, Any]:
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


def checkpoint_state(state: dict[str, Any], version: int, fresh: dict[str, Any], cfg: Config,
                     batched: bool) -> dict[str, Any]:
    """A checkpoint's state dict of format `version` (2 or later; format 1's: `from_format_1` first) in today's
    format. `fresh`: the state dict of a new run of `cfg` (a format 3-4 file's state is completed from it);
    batched: the file holds a batch of runs (a leading [S] axis)."""
    fresh = {**fresh, "emitter": _flat(fresh["emitter"])}  # as formats 4-5 held it
    if version < 4:
        state = _from_format_3(state, fresh, cfg)
    if version < 5:
        state = _from_format_4(state, fresh, batched)
    if version < 6:
        state = _from_format_5(state)
    return _from_format_9(_from_format_8(_from_format_7(_from_format_6(state), cfg)))
