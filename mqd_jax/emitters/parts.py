"""A model emitter's optional parts: each an object with its own state, run in a chain.

`ModelEmitter(inner, rule, surrogate, parts=(Steering(), Anchoring("auto"), Fallback()))` keeps its core (the
inner emitter's pool, the surrogate's predictions, the rule's choice, warm-up) and runs its parts in order at
each stage of a generation, as optax's `chain` runs gradient transformations:

    pool        part.pool(key, state, pool, view)             -> (pool, info)  steering replaces rows of the pool
    predict     part.predicted(state, y, candidates, view)    -> (y, info)     anchoring changes the predictions
    judge       part.judged(state, judged, view)              -> judged        curiosity reweighs the parents
    share       part.share(state) (a `Share`)                 -> float32       the model's share of the rollouts
    update      part.update(state, info, proposal, evaluated) -> state         after the rollouts
    report      part.report(state, info, proposal, evaluated) -> metrics       the metrics it declares

Every stage has a neutral default here, so a part writes only its own (a part that does not subclass `Part` may
leave out `judged` and `sized`, added in 0.23). What its pool and predict stages return
as info holds one row per pool candidate (each leaf's leading axis); the emitter keeps the chosen rows and hands
both back to `update` and `report` as the pair `info` = (pool stage's, predict stage's)
(`ModelInfo.parts[part.name]`). The chain gates warm-up once: until the emitter's warm-up is over, a part whose
`learns_in_warm_up` is False keeps its state (its `update` is not used); `report` sees the state the
generation was chosen with. A part whose state is sized by the repertoire sets `sized = True` and takes
`init(key, task, capacity)`, as a sized emitter does (`core.emitter.init_emitter` initializes either).

A part that takes a share of the rows for the model's choice is a `Share` (its `share(state)` a float32 in
[0, 1]): `Fallback` (adaptive pursuit between the model's choice and the inner emitter's own candidates) and
`StepAside` (0 while the model explains no more than chance); the model's share of a generation is the product
of the chain's shares. `Steering.pursuit` takes any `Share` for the share of its rows it steers.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import jax
import jax.numpy as jnp

from mqd_jax.core import pytree
from mqd_jax.core.emitter import Evaluated, Proposal
from mqd_jax.core.params import Params
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.task import Task


@dataclasses.dataclass(frozen=True)
class View:
    """What a part sees of the generation being proposed (inside the traced program).

    Attributes:
      model: the surrogate as the emitter reads it (`protocol.hooks`); surrogate: its state.
      repertoire, task, params: the run's (`params.emitter` is the model emitter's own).
      num: the generation's rollouts; warm_up: bool, the emitter is still warming up.
    """

    model: Any
    surrogate: Any
    repertoire: Repertoire
    task: Task
    params: Params
    num: int
    warm_up: jax.Array


@pytree.dataclass
class Pooled:
    """A pool's candidates as the predict stage sees them (N rows).

    Attributes:
      actions: [N, n]; parents: [N] int32 slots (-1: none) or None; x: [N, ...] the surrogate's inputs;
      members: [E, N, d + 1] the surrogate's plain predictions before its `overrule` (the gate).
    """

    actions: jax.Array
    parents: jax.Array | None
    x: jax.Array
    members: jax.Array


@pytree.dataclass
class ModelInfo:
    """What a model emitter's proposal carries from `propose` to `update` (`Proposal.info`), per kept row [num].

    A rule's `update(key, state, proposal, evaluated)` reads it as `proposal.info`.

    Attributes:
      inner: the inner emitter's own info, its rows kept.
      predicted_behaviors: [num, d] the model's predictions of the kept rows (as the rule judged them).
      predicted_distance: [num] from each to the nearest skill (the opener AUC's score).
      from_model: [num] bool, the row is the rule's choice (not a share's fill from the inner emitter's own).
      discarded: int32, the candidates the model turned down.
      validity: [num] the validity classifier's probability of a usable rollout, or None without one.
      parts: {part.name: (its pool stage's info, its predict stage's info)}, rows kept.
      parents: [num] int32 the kept rows' parents' slots (-1: none), or None where the inner emitter names none
        (a run's `update` is not given `Proposal.parents`: a rule or a part reads them here).
    """

    inner: Any
    predicted_behaviors: jax.Array
    predicted_distance: jax.Array
    from_model: jax.Array
    discarded: jax.Array
    validity: jax.Array | None = None
    parts: dict[str, Any] = dataclasses.field(default_factory=dict)
    parents: jax.Array | None = None


class Part:
    """The neutral part: every stage leaves the generation as it is. A part subclasses it (or has the same
    methods) and writes its own stages (the module's doc).

    Class attributes:
      name: its key in the emitter's state, the proposal's info and the chain (one part of each name).
      learns_in_warm_up: its `update` is used during warm-up too (else the chain keeps its state then).
      needs_ranking: why it needs a ranking rule (best rows first), or None where it does not.
      shares: it takes a share of the rows (`Share`).
      sized: its `init` takes the repertoire's capacity too: `init(key, task, capacity)`.
    """

    name: ClassVar[str] = "part"
    learns_in_warm_up: ClassVar[bool] = False
    needs_ranking: ClassVar[str | None] = None
    shares: ClassVar[bool] = False
    sized: ClassVar[bool] = False

    def init(self, key: jax.Array, task: Task) -> Any:
        return ()

    def metrics(self) -> dict[str, Any]:
        """{name: dtype} of the metrics `report` returns."""
        return {}

    def check_run(self, pool_size: int, num: int) -> None:
        """ValueError where a run whose pool holds `pool_size` candidates for `num` rollouts cannot use it."""

    def pool(self, key: jax.Array, state: Any, pool: Proposal, view: View) -> tuple[Proposal, Any]:
        return pool, ()

    def predicted(self, state: Any, y: jax.Array, candidates: Pooled, view: View) -> tuple[jax.Array, Any]:
        return y, ()

    def judged(self, state: Any, judged: Any, view: View) -> Any:
        """The model's view of the pool (`acquisition.Judged`) as the rule will read it."""
        return judged

    def update(self, state: Any, info: Any, proposal: Proposal, evaluated: Evaluated) -> Any:
        return state

    def report(self, state: Any, info: Any, proposal: Proposal, evaluated: Evaluated) -> dict[str, jax.Array]:
        return {}


class Share(Part):
    """A part that takes a share of a generation's rows for one side (the model's choice; steered children),
    learned from which side's rollouts opened niches or from the model's skill: `Fallback`, `StepAside`.

    A share writes `init(key, task)`, `share(state)` (float32 in [0, 1]) and `learn(state, first, predicted,
    evaluated)`: the state after a generation whose rows [P] `first` came from the first side, the model having
    predicted their behaviors [P, d]. In a chain, the first side is the rule's choice (`ModelInfo.from_model`);
    as `Steering.pursuit`, the steered children.
    """

    shares = True

    def share(self, state: Any) -> jax.Array:
        raise NotImplementedError

    def learn(self, state: Any, first: jax.Array, predicted: jax.Array, evaluated: Evaluated) -> Any:
        raise NotImplementedError

    def update(self, state: Any, info: Any, proposal: Proposal, evaluated: Evaluated) -> Any:
        return self.learn(state, proposal.info.from_model, proposal.info.predicted_behaviors, evaluated)


def is_share(value: Any) -> bool:
    """Whether `value` has a share's functions (`Share`)."""
    return all(callable(getattr(value, name, None)) for name in ("init", "share", "learn"))


def check_chain(parts: tuple[Any, ...], ranked: bool, owner: str, metrics: list[dict[str, Any]]) -> None:
    """ValueError unless `parts` is a tuple of parts with distinct names, each needing a ranking rule only with
    one (`ranked`), whose metrics clash neither with each other's nor with the others' `metrics` ({name: dtype}
    each: the emitter's own, its surrogate's, its inner emitter's)."""
    if not isinstance(parts, tuple):
        raise ValueError(f"{owner}.parts={parts!r} is invalid: expected a tuple of parts (mqd_jax.emitters.parts)")
    names = []
    for part in parts:
        missing = [m for m in ("name", "init", "pool", "predicted", "update", "report", "metrics", "check_run")
                   if not hasattr(part, m)]
        if missing:
            raise ValueError(f"{owner}.parts: {part!r} is not a part: it lacks {missing} (subclass "
                             "mqd_jax.emitters.parts.Part, whose stages are neutral)")
        if part.needs_ranking and not ranked:
            raise ValueError(f"{owner}.parts: {part!r} needs a ranking acquisition rule ({part.needs_ranking}), "
                             "not one whose rows are not ranked, as Threshold's")
        names.append(part.name)
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ValueError(f"{owner}.parts: more than one part named {twice}: a chain holds one of each")
    declared = [set(m) for m in metrics] + [set(part.metrics()) for part in parts]
    clash = {name for i, a in enumerate(declared) for b in declared[i + 1:] for name in a & b}
    if clash:
        raise ValueError(f"{owner}: the metrics {sorted(clash)} are declared by more than one of its parts (the "
                         "model, the surrogate, the inner emitter, the chain's parts)")


def judged(parts: tuple[Any, ...], states: dict[str, Any], judgement: Any, view: View) -> Any:
    """The model's view of the pool (`acquisition.Judged`) as the chain's judge stages leave it, in order."""
    for part in parts:
        stage = getattr(part, "judged", None)
        if stage is not None:
            judgement = stage(states[part.name], judgement, view)
    return judgement


def shared(parts: tuple[Any, ...]) -> bool:
    """Whether a part of the chain takes a share of the rows (`Share`; the `model_share` metric)."""
    return any(part.shares for part in parts)


def kept(info: Any, rows: jax.Array, pool_size: int) -> Any:
    """`info` with the chosen rows [num] of every leaf whose leading axis is the pool's (`pool_size`: a part's
    every leaf, the inner emitter's per-candidate ones), the other leaves as they are."""
    return jax.tree.map(lambda x: x[rows] if jnp.ndim(x) and jnp.shape(x)[0] == pool_size else x, info)


def model_share(parts: tuple[Any, ...], states: dict[str, Any]) -> jax.Array | None:
    """The model's share of the generation: the product of the chain's shares (1 to start), or None where no
    part takes one."""
    if not shared(parts):
        return None
    share = jnp.float32(1.0)
    for part in parts:
        if part.shares:
            share = share * part.share(states[part.name])
    return share


def updated(parts: tuple[Any, ...], states: dict[str, Any], infos: dict[str, Any], proposal: Proposal,
            evaluated: Evaluated, warm_up: jax.Array) -> tuple[dict[str, Any], dict[str, jax.Array]]:
    """The parts' states after a generation (warm-up gated once: the parts that do not learn in it keep their
    states) and their metrics (reported from the states the generation was chosen with)."""
    metrics: dict[str, jax.Array] = {}
    for part in parts:
        metrics.update(part.report(states[part.name], infos[part.name], proposal, evaluated))
    new = {part.name: part.update(states[part.name], infos[part.name], proposal, evaluated)
           for part in parts if part.learns_in_warm_up}
    gated = [part for part in parts if not part.learns_in_warm_up]
    if gated:
        new.update(jax.lax.cond(
            warm_up, lambda: {part.name: states[part.name] for part in gated},
            lambda: {part.name: part.update(states[part.name], infos[part.name], proposal, evaluated)
                     for part in gated}))
    return new, metrics
