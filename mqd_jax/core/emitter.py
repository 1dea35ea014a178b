"""Emitters: the parts of a search that propose candidates and learn from their rollouts.

An emitter (like optax's `GradientTransformation` or QDax's `Emitter`) is a
frozen dataclass of static settings with three pure functions over a state of
its own (any pytree, e.g. a `flax.struct` dataclass):

    state = emitter.init(key, task)            # a `sized` one: init(key, task, capacity)
    proposal = emitter.propose(key, state, repertoire, task, params, num)
    state, metrics = emitter.update(key, state, proposal, evaluated, repertoire, task, params)

Static settings are the dataclass's fields; traced parameters (float32 scalars a
run may `vmap` over) are the emitter's own: `default_params()` gives them from
its fields, `check_params` refuses bad concrete values, and `propose`/`update`
read them as `params.emitter.<name>` (`mqd_jax.core.params.Params`; the engine's
`params.t_dist` beside them). `check_run(population_size, max_generations)`
refuses, before anything is traced, a run the emitter cannot serve; `check_task(task)`, a task it cannot;
`pool_size(num)` says how many candidates it judges for `num` proposals (a run's memory estimate).

`propose` gives `num` candidate actions and which of them to roll out;
`update` sees their results (`Evaluated`) and the repertoire after they were
inserted, and returns the scalars named by `metrics()` (they join a run's
per-generation metrics). All three are traced inside one jitted generation:
they must be jittable and vmappable (no Python branching on array values).
Emitters compose by wrapping: `mqd_jax.emitters.model_emitter.ModelEmitter(IsoLine())`
filters or ranks what the inner emitter proposes.

This module holds the protocol; `mqd_jax.emitters.baselines` the paper's baselines, `Uniform`
(RANDOM) and `IsoLine` (QD).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import pytree
from mqd_jax.core.params import Params
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.task import Task


@pytree.dataclass
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
      features: [num, f] the task's features of the actions (`Task.features`) where the emitter computed them,
        or None. Where the emitter `keeps_features`, the repertoire keeps them for the skills the candidates
        become (the run computes them where they are None); `update` is given them.
    """

    actions: jax.Array
    rollout: jax.Array
    info: Any = ()
    parents: jax.Array | None = None
    features: jax.Array | None = None


@pytree.dataclass
class Evaluated:
    """A proposal's outcome, as `Emitter.update` sees it (num candidates).

    Attributes:
      behaviors: [num, d], qualities: [num]: the rollouts' results; zeros
        where `usable` is False.
      usable: [num] bool, rolled out and returned a valid, finite result.
      status: [num] int32 `repertoire.AddStatus` of each candidate's insertion.
      auxiliary: [num, m] the task's auxiliary outputs (`Task.auxiliary`; m = 0 for a
        task without them); zeros where `usable` is False.
    """

    behaviors: jax.Array
    qualities: jax.Array
    usable: jax.Array
    status: jax.Array
    auxiliary: Any = None


def action_bounds(task: Task) -> tuple[jax.Array, jax.Array]:
    """The task's action box as float32 arrays low [n], high [n]."""
    return jnp.asarray(task.action_low, jnp.float32), jnp.asarray(task.action_high, jnp.float32)


@dataclasses.dataclass(frozen=True)
class Emitter:
    """Base class of emitters: subclass it as a frozen dataclass and implement `propose`.

    The defaults: no state, an `update` that changes nothing and no metrics. An emitter whose state depends on
    the repertoire's size sets the class attribute `sized = True` and takes `init(key, task, capacity)` (the
    run passes `Config.capacity`; `init_emitter` calls either kind).
    """

    sized = False

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

    def check_task(self, task: Task) -> None:
        """Raises ValueError if the emitter cannot serve this task (default: it can)."""
        del task

    def keeps_features(self, task: Task) -> bool:
        """Whether the repertoire keeps the task's features of each skill for this emitter (`Repertoire.features`:
        computed once per skill, from `Proposal.features`; default: no)."""
        del task
        return False

    def pool_size(self, num: int) -> int:
        """How many candidates the emitter makes and judges to propose `num` (default: `num`); sizes the memory
        estimate a run is checked against before it is traced (`mqd_jax.core.sizes`)."""
        return num

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

    def problems(self, metrics: Mapping[str, np.ndarray]) -> list[str]:
        """What went wrong in a run without an error, read from its metrics (numpy arrays [G], or [R, G] for a
        batch): one message each, which `diagnostics.warn` emits as a `RunWarning` (default: none)."""
        del metrics
        return []

    def forward_model(self, state: Any, task: Task) -> tuple[Callable[[jax.Array], jax.Array], jax.Array] | None:
        """The emitter's learned model of behavior, as it stands in `state`: (predict, trained), predict mapping
        an action [n] to its predicted behavior [d] (differentiable: `adapt(..., "model")` takes its Jacobian)
        and trained a bool array (the model has trained); None for an emitter without one (default)."""
        del state, task
        return None


def init_emitter(emitter: Emitter, key: jax.Array, task: Task, capacity: int) -> Any:
    """`emitter`'s initial state (or a model emitter's part's, `mqd_jax.emitters.parts`): `init(key, task,
    capacity)` for a `sized` one, else `init(key, task)` (also for a part written before parts could be sized)."""
    return emitter.init(key, task, capacity) if getattr(emitter, "sized", False) else emitter.init(key, task)
