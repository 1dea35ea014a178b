"""A model of outcomes that jump: a gate (does the action act at all?) times the forward model's regression.

Where an outcome is discontinuous in the action, a regression network smooths
across the jump: a push that misses the object leaves it where it was, one
that touches it moves it, and a network of the raw action predicts something in
between for both. The forward model also trains on the repertoire, whose skills
nearly all act (a skill that leaves the object in place is one niche), so it
has hardly seen an action that does not.

`Gate` learns from every usable rollout (a ring buffer of the latest), on the
task's auxiliary outputs (`Task.auxiliary`: what a rollout observes on the
way): one network, one head per auxiliary output, on the mean-squared error
of all of them (a multi-task loss: where the object was part-way shapes the
hidden layer that the gate's head reads). Head `label` is the gate: the task
gives +1 where the action acted (the object moved) and -1 where it did not;
(output + 1) / 2 is the probability that it acts. The outcome of an action
that does not act is the *null outcome*: the mean behavior and quality of the
rollouts labelled -1 so far. `Surrogate(gate=...)` predicts the null outcome
for a candidate whose probability is below 1/2 and the forward model's
prediction for the others. Until the buffer has held both labels the gate
passes every candidate, so on a task whose rollouts all act (or none) the
predictions are the forward model's; on a task without auxiliary outputs the
gate does nothing at all (a run is the same as without it).

The network's inputs are the surrogate's (normalized actions, with
`Surrogate(features=True)` the task's features), computed once per rollout
when it enters the buffer.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from mqd_jax.core import archive as archive_lib
from mqd_jax.core import pytree
from mqd_jax.core.checks import is_int
from mqd_jax.core.task import Task
from mqd_jax.surrogate import model


@pytree.dataclass
class GateState:
    """The gate's state.

    Attributes:
      model: its network (`model.ModelState`, one member, m outputs: the task's auxiliary outputs).
      buffer: the latest usable rollouts (`archive.Archive` of `buffer_size` rows: the network's inputs
        [B, n (+ f)] as actions, the auxiliary outputs [B, m] as behaviors, and 1.0 as quality).
      null_sum: [d + 1] the summed behavior and quality of the rollouts labelled -1.
      counts: [2] int32, the rollouts labelled -1 and +1 so far.
    """

    model: model.ModelState
    buffer: archive_lib.Archive
    null_sum: jax.Array
    counts: jax.Array


@dataclasses.dataclass(frozen=True)
class Gate:
    """Whether an action acts at all, learned from the rollouts' auxiliary outputs (see the module's doc).

    Attributes:
      label: the auxiliary output that gates: +1 the action acted, -1 it did not (push tasks: "moved").
      hidden_size: its hidden units.
      buffer_size: the rollouts it remembers (a ring buffer).
      batch_size, num_batches: its Adam steps per generation (at the surrogate's learning rate).
    """

    label: str = "moved"
    hidden_size: int = 32
    buffer_size: int = 4096
    batch_size: int = 64
    num_batches: int = 100

    def __post_init__(self) -> None:
        if not (isinstance(self.label, str) and self.label):
            raise ValueError(f"Gate.label={self.label!r} is invalid: expected the name of an auxiliary output")
        for name in ("hidden_size", "buffer_size", "batch_size", "num_batches"):
            value = getattr(self, name)
            if not (is_int(value) and value >= 1):
                raise ValueError(f"Gate.{name}={value!r} is invalid: expected an int >= 1")

    def serves(self, task: Task) -> bool:
        """Whether the gate acts on `task`: it returns auxiliary outputs (a task without any: the gate does
        nothing, a run is the same as without it)."""
        return bool(task.auxiliary)

    def check_task(self, task: Task) -> None:
        """Raises ValueError if the task returns auxiliary outputs but not `label`."""
        if task.auxiliary and self.label not in task.auxiliary:
            raise ValueError(f"Gate(label={self.label!r}): {type(task).__name__} returns the auxiliary outputs "
                             f"{task.auxiliary} (Task.auxiliary), not {self.label!r}: name one of them as the label")

    def init(self, key: jax.Array, task: Task, inputs: int) -> GateState:
        m = len(task.auxiliary)
        return GateState(model=model.init(key, self.hidden_size, task, out_size=m, input_size=inputs),
                         buffer=archive_lib.Archive.empty(self.buffer_size, inputs, m),
                         null_sum=jnp.zeros(task.behavior_dim + 1, jnp.float32), counts=jnp.zeros(2, jnp.int32))

    def probability(self, state: GateState, inputs: jax.Array, task: Task) -> jax.Array:
        """[N] the probability that each candidate (the network's inputs [N, n (+ f)]) acts; 1 until both
        labels were seen."""
        output = model.apply_members(state.model, inputs)[0, :, task.auxiliary.index(self.label)]
        return jnp.where((state.counts > 0).all(), (jnp.clip(output, -1.0, 1.0) + 1.0) / 2.0, 1.0)

    def null(self, state: GateState) -> jax.Array:
        """[d + 1] the null outcome: the mean behavior and quality of the rollouts labelled -1 (zeros before one)."""
        return state.null_sum / jnp.maximum(state.counts[0], 1)

    def gated(self, state: GateState, inputs: jax.Array, predictions: jax.Array, task: Task) -> jax.Array:
        """Predictions [E, N, d + 1] with the candidates (inputs [N, n (+ f)]) that the gate says do not act
        moved to the null outcome."""
        acts = self.probability(state, inputs, task) >= 0.5
        return jnp.where(acts[None, :, None], predictions, self.null(state))

    def update(self, key: jax.Array, state: GateState, inputs: jax.Array, auxiliary: jax.Array, outcomes: jax.Array,
               usable: jax.Array, task: Task, learning_rate: jax.Array) -> GateState:
        """Remembers the usable rows of the rollouts (inputs [P, n (+ f)], auxiliary [P, m], behavior and quality
        outcomes [P, d + 1]), adds those labelled -1 to the null outcome, then trains (once it has data)."""
        label = auxiliary[:, task.auxiliary.index(self.label)]
        acted = label > 0
        buffer = archive_lib.push(state.buffer, inputs, auxiliary, jnp.ones(inputs.shape[0], jnp.float32), usable)
        null_sum = state.null_sum + jnp.where((usable & ~acted)[:, None], outcomes, 0.0).sum(axis=0)
        counts = state.counts + jnp.stack([(usable & ~acted).sum(), (usable & acted).sum()]).astype(jnp.int32)
        filled = jnp.minimum(buffer.total, self.buffer_size)
        trained = jax.lax.cond(
            filled > 0,
            lambda: model.fit(state.model, key, buffer.actions, buffer.behaviors, filled, learning_rate,
                              self.batch_size, self.num_batches)[0],
            lambda: state.model)
        return GateState(model=trained, buffer=buffer, null_sum=null_sum, counts=counts)
