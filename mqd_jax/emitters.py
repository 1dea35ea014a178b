"""Emitters: the parts of a search that propose candidates and learn from their rollouts.

An emitter (like optax's `GradientTransformation` or QDax's `Emitter`) is a
frozen dataclass of static settings with three pure functions over a state of
its own (any pytree, e.g. a `flax.struct` dataclass):

    state = emitter.init(key, task)
    proposal = emitter.propose(key, state, repertoire, task, params, num)
    state, metrics = emitter.update(key, state, proposal, evaluated, repertoire, task, params)

Static settings are the dataclass's fields; traced parameters (float32 scalars a
run may `vmap` over) are the emitter's own: `default_params()` gives them from
its fields, `check_params` refuses bad concrete values, and `propose`/`update`
read them as `params.emitter.<name>` (`mqd_jax.params.Params`; the engine's
`params.t_dist` beside them). `check_run(population_size, max_generations)`
refuses, before anything is traced, a run the emitter cannot serve.

`propose` gives `num` candidate actions and which of them to roll out;
`update` sees their results (`Evaluated`) and the repertoire after they were
inserted, and returns the scalars named by `metrics()` (they join a run's
per-generation metrics). All three are traced inside one jitted generation:
they must be jittable and vmappable (no Python branching on array values).
Emitters compose by wrapping: `mqd_jax.model_emitter.ModelEmitter(IsoLine())`
filters or ranks what the inner emitter proposes.

This module holds the protocol and the two emitters of the paper's baselines:
`Uniform` (RANDOM) and `IsoLine` (QD).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from mqd_jax import selection, variation
from mqd_jax.checks import check_traced, is_real
from mqd_jax.params import Params
from mqd_jax.repertoire import Repertoire
from mqd_jax.task import Task


@struct.dataclass
class Proposal:
    """What `Emitter.propose` returns (num candidates).

    Attributes:
      actions: [num, n] candidate actions inside the task's action box.
      rollout: [num] bool, the candidates worth a rollout; the others are not
        evaluated (a backend that can skip rollouts skips them) and not inserted.
      info: any pytree the emitter hands to its own `update` (e.g. the model's
        predictions). A wrapper that keeps some rows of its inner emitter's
        proposal keeps the same rows of every leaf whose leading axis is num.
      parents: [num] int32, the repertoire slot of the skill each candidate was
        varied from (its first parent), -1 for a candidate with none (uniform);
        or None where the emitter does not say. Read by a wrapper
        (`ModelEmitter` anchors its predictions there); `update` is not given it.
    """

    actions: jax.Array
    rollout: jax.Array
    info: Any = ()
    parents: jax.Array | None = None


@struct.dataclass
class Evaluated:
    """A proposal's outcome, as `Emitter.update` sees it (num candidates).

    Attributes:
      behaviors: [num, d], qualities: [num]: the rollouts' results; zeros
        where `usable` is False.
      usable: [num] bool, rolled out and returned a valid, finite result.
      status: [num] int32 `repertoire.AddStatus` of each candidate's insertion.
    """

    behaviors: jax.Array
    qualities: jax.Array
    usable: jax.Array
    status: jax.Array


def action_bounds(task: Task) -> tuple[jax.Array, jax.Array]:
    """The task's action box as float32 arrays low [n], high [n]."""
    return jnp.asarray(task.action_low, jnp.float32), jnp.asarray(task.action_high, jnp.float32)


@dataclasses.dataclass(frozen=True)
class Emitter:
    """Base class of emitters: subclass it as a frozen dataclass and implement `propose`.

    The defaults: no state, an `update` that changes nothing and no metrics.
    """

    def init(self, key: jax.Array, task: Task) -> Any:
        """The emitter's state before the first generation (a pytree; default: none)."""
        del key, task
        return ()

    def default_params(self) -> Any:
        """The emitter's traced parameters (a pytree of float32 scalars), from its fields (default: none)."""
        return ()

    def check_params(self, params: Any) -> None:
        """Raises ValueError, naming the parameter, for a bad concrete value of `default_params()`'s kind."""
        del params

    def check_run(self, population_size: int, max_generations: int) -> None:
        """Raises ValueError if the emitter cannot serve a run of this size (default: it can)."""
        del population_size, max_generations

    def propose(self, key: jax.Array, state: Any, repertoire: Repertoire, task: Task, params: Params,
                num: int) -> Proposal:
        """`num` candidates from the repertoire as it stands (see `Proposal`)."""
        raise NotImplementedError

    def update(self, key: jax.Array, state: Any, proposal: Proposal, evaluated: Evaluated, repertoire: Repertoire,
               task: Task, params: Params) -> tuple[Any, dict[str, jax.Array]]:
        """The state after the proposal's rollouts, and this generation's metrics (scalars named in `metrics`)."""
        del key, proposal, evaluated, repertoire, task, params
        return state, {}

    def metrics(self) -> dict[str, Any]:
        """{name: dtype} of the scalars `update` returns (default: none)."""
        return {}


def _uniform_key(key: jax.Array) -> jax.Array:
    # The first of IsoLine's three subkeys: RANDOM's candidates equal QD's first generation for the same key.
    return jax.random.split(key, 3)[0]


@dataclasses.dataclass(frozen=True)
class Uniform(Emitter):
    """RANDOM: actions uniform in the task's action box, all rolled out."""

    def propose(self, key: jax.Array, state: Any, repertoire: Repertoire, task: Task, params: Params,
                num: int) -> Proposal:
        return Proposal(variation.uniform(_uniform_key(key), num, *action_bounds(task)), jnp.ones(num, bool),
                        parents=jnp.full(num, -1, jnp.int32))


@struct.dataclass
class IsoLineParams:
    """IsoLine's traced parameters: the iso step `iso_sigma` (x the action range) and the line step `line_sigma`."""

    iso_sigma: jax.Array
    line_sigma: jax.Array


@dataclasses.dataclass(frozen=True)
class IsoLine(Emitter):
    """QD: parents drawn in proportion to novelty, iso+line children (Vassiliades & Mouret 2018):
    `x1 + iso_sigma (high - low) N(0, I) + line_sigma (x2 - x1) N(0, 1)`.

    Uniform actions while the repertoire is empty; every candidate is rolled out. A child's `parents` entry is
    its first parent x1, from which the iso noise starts (-1 for a uniform action).

    `scales` (finite floats > 0): the children come in equal parts (the first parts one larger where `num` does
    not divide), part i with both steps times `scales[i]`, each part from its own key `fold_in(key, i)`. One
    scale (the default, (1.0,), the paper's QD) draws from `key` itself.

    `iso_sigma`, `line_sigma` (finite floats >= 0): the defaults of its traced parameters (`IsoLineParams`).
    """

    scales: tuple[float, ...] = (1.0,)
    iso_sigma: float = 0.02
    line_sigma: float = 0.1

    def __post_init__(self) -> None:
        if not (isinstance(self.scales, tuple) and self.scales and all(is_real(s) and s > 0 for s in self.scales)):
            raise ValueError(f"IsoLine.scales={self.scales!r} is invalid: expected a non-empty tuple of finite "
                             "floats > 0")
        for name in ("iso_sigma", "line_sigma"):
            if not (is_real(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"IsoLine.{name}={getattr(self, name)!r} is invalid: expected a finite float >= 0")

    def default_params(self) -> IsoLineParams:
        return IsoLineParams(jnp.float32(self.iso_sigma), jnp.float32(self.line_sigma))

    def check_params(self, params: IsoLineParams) -> None:
        for name in ("iso_sigma", "line_sigma"):
            check_traced("IsoLine.params", name, getattr(params, name))

    def propose(self, key: jax.Array, state: Any, repertoire: Repertoire, task: Task, params: Params,
                num: int) -> Proposal:
        if len(self.scales) == 1:
            return self._children(key, repertoire, task, params, self.scales[0], num)
        sizes = [num // len(self.scales) + (i < num % len(self.scales)) for i in range(len(self.scales))]
        parts = [self._children(jax.random.fold_in(key, i), repertoire, task, params, scale, size)
                 for i, (scale, size) in enumerate(zip(self.scales, sizes, strict=True))]
        return jax.tree.map(lambda *rows: jnp.concatenate(rows), *parts)

    @staticmethod
    def _children(key: jax.Array, repertoire: Repertoire, task: Task, params: Params, scale: float,
                  num: int) -> Proposal:
        """`num` children with both steps times `scale`."""
        low, high = action_bounds(task)
        _, k_parents, k_vary = jax.random.split(key, 3)
        fresh = variation.uniform(_uniform_key(key), num, low, high)
        parents = selection.sample_parents(k_parents, repertoire.novelty, repertoire.valid, 2 * num)
        x = repertoire.actions[parents].reshape(2, num, -1)
        children = variation.iso_line(k_vary, x[0], x[1], params.emitter.iso_sigma * scale,
                                      params.emitter.line_sigma * scale, low, high)
        bred = repertoire.count > 0
        return Proposal(jnp.where(bred, children, fresh), jnp.ones(num, bool),
                        parents=jnp.where(bred, parents[:num], -1).astype(jnp.int32))
