"""M-QD's forward model phi(a) = (b, q) and its online training.

The network (paper, "Model-Based Quality-Diversity Search"): one hidden layer
with ReLU, tanh on the outputs. It works in normalized units: actions are
mapped from their bounds to [-1, 1], behaviors from the behavior box to
[-1, 1], and qualities from the task's fixed `quality_range` to [-1, 1], so
the tanh outputs cover exactly the bounded spaces. `predict` maps back to real
units and is the one function the filter and skill adaptation both use.

An ensemble of E such networks (E = 1 is the paper's model) has every
parameter with a leading [E] axis; the members are applied and trained with
`jax.vmap`. `predict` is the members' mean; `predict_members` gives each
member's prediction, whose spread measures the model's uncertainty.

Training (`mqd_jax.emitters.model_emitter` calls it after every generation once warm-up
is over): `num_batches` Adam steps on the mean-squared error in normalized
units, each member on its own `batch_size` rows drawn uniformly (with
replacement) from the training data (the repertoire, or a buffer of rollouts).

With `features=True` the network's inputs are the normalized actions followed
by the task's features of them (`Task.features`: what the task can compute
without physics); a task without features gives the same inputs either way.

Flax's `linen` and optax are imported when a model is first built (`init`), so
`import mqd_jax` does not pay for them in a run without a model.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import pytree, selection
from mqd_jax.core.archive import Archive
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.task import Task, feature_dim


@functools.cache
def _mlp() -> type:
    """The network's Flax module class (Flax's linen imported on first use)."""
    import flax.linen as nn

    class MLP(nn.Module):
        """normalized actions [..., n] -> normalized (behavior, quality) [..., d + 1]."""

        hidden_size: int
        out_size: int

        @nn.compact
        def __call__(self, x: jax.Array) -> jax.Array:
            x = nn.relu(nn.Dense(self.hidden_size)(x))
            return jnp.tanh(nn.Dense(self.out_size)(x))

    return MLP


def mlp(hidden_size: int, out_size: int) -> Any:
    """The network: one hidden layer of `hidden_size` ReLU units, `out_size` tanh outputs (a Flax module)."""
    return _mlp()(hidden_size=hidden_size, out_size=out_size)


@pytree.dataclass
class ModelState:
    """The model's parameters and optimizer state.

    Attributes:
      params: Flax variables of the E members' MLPs: Dense_0 kernel [E, n, H],
        bias [E, H]; Dense_1 kernel [E, H, d + 1], bias [E, d + 1].
      opt_state: `optax.adam`'s state with its hyperparameters injected
        (`optax.inject_hyperparams`): the learning rate is a traced value.
      steps: int32, training steps taken so far.
    """

    params: Any
    opt_state: Any
    steps: jax.Array


@functools.cache
def _optimizer() -> Any:
    """Adam with its learning rate in the optimizer state, so that `train` can set it from a traced parameter.
    Its other hyperparameters stay Python constants, folded into the program as optax.adam's are."""
    import optax

    return optax.inject_hyperparams(optax.adam, static_args=("b1", "b2", "eps", "eps_root"))(learning_rate=0.0)


def network(hidden_size: int, task: Task) -> Any:
    """phi's network for `task`: d + 1 outputs."""
    return mlp(hidden_size, task.behavior_dim + 1)


def _network_of(model: ModelState) -> Any:
    """The network `model`'s parameters belong to (its sizes read from their shapes)."""
    layers = model.params["params"]
    return mlp(layers["Dense_0"]["bias"].shape[-1], layers["Dense_1"]["bias"].shape[-1])


def _bounds(task: Task) -> tuple[jax.Array, jax.Array]:
    """Low and high of the model's outputs in real units, [d + 1] each."""
    q_low, q_high = task.quality_range
    low = jnp.asarray((*task.behavior_low, q_low), jnp.float32)
    high = jnp.asarray((*task.behavior_high, q_high), jnp.float32)
    return low, high


def _to_unit(x: jax.Array, low: jax.Array, high: jax.Array) -> jax.Array:
    return 2.0 * (x - low) / (high - low) - 1.0


def normalize_actions(actions: jax.Array, task: Task) -> jax.Array:
    """actions [..., n] in real units -> [-1, 1] per dimension."""
    low, high = jnp.asarray(task.action_low, jnp.float32), jnp.asarray(task.action_high, jnp.float32)
    return _to_unit(actions, low, high)


def normalize_targets(behaviors: jax.Array, qualities: jax.Array, task: Task) -> jax.Array:
    """behaviors [..., d] and qualities [...] -> normalized targets [..., d + 1]."""
    return _to_unit(jnp.concatenate([behaviors, qualities[..., None]], axis=-1), *_bounds(task))


def inputs(actions: jax.Array, task: Task, features: bool = False) -> jax.Array:
    """The network's inputs: actions [..., n] normalized, then with `features` the task's features [..., f]."""
    if not features:
        return normalize_actions(actions, task)
    flat = actions.reshape(-1, actions.shape[-1])
    return inputs_with(actions, task.features(flat).reshape(*actions.shape[:-1], -1), task)


def inputs_with(actions: jax.Array, features: jax.Array, task: Task) -> jax.Array:
    """The network's inputs of actions [..., n] whose features [..., f] are known (`Repertoire.features`)."""
    return jnp.concatenate([normalize_actions(actions, task), features], axis=-1)


def init(key: jax.Array, hidden_size: int, task: Task, ensemble_size: int = 1,
         out_size: int | None = None, features: bool = False, input_size: int | None = None) -> ModelState:
    """Random parameters of `ensemble_size` members (Flax's default initialisers, one key each) and a fresh Adam
    state. A single member is initialised from `key` itself. `out_size`: the outputs, d + 1 (phi) unless given
    (a network of the same kind that predicts something else, as `mqd_jax.surrogate.validity`'s classifier).
    The inputs: n, n + f with `features` (the task's features), or `input_size` where given."""
    net = network(hidden_size, task) if out_size is None else mlp(hidden_size, out_size)
    if input_size is None:
        input_size = task.action_dim + (feature_dim(task) if features else 0)
    x = jnp.zeros((1, input_size), jnp.float32)
    keys = key[None] if ensemble_size == 1 else jax.random.split(key, ensemble_size)
    params = jax.vmap(lambda k: net.init(k, x))(keys)
    return ModelState(params=params, opt_state=_optimizer().init(params), steps=jnp.int32(0))


def ensemble_size(model: ModelState) -> int:
    """E, the number of members."""
    return model.params["params"]["Dense_0"]["bias"].shape[0]


def predict_members(model: ModelState, actions: jax.Array, task: Task, features: bool = False,
                    given: jax.Array | None = None) -> jax.Array:
    """Each member's phi in real units: actions [..., n] -> [E, ..., d + 1] (behavior, then quality). `given`:
    the network's inputs of the actions where already computed (`inputs`)."""
    y = apply_members(model, inputs(actions, task, features) if given is None else given)
    low, high = _bounds(task)
    return low + (y + 1.0) * (high - low) / 2.0


def apply_members(model: ModelState, inputs: jax.Array) -> jax.Array:
    """Each member's raw outputs in [-1, 1]: inputs [..., n] (normalized) -> [E, ..., out]."""
    net = _network_of(model)
    return jax.vmap(lambda p: net.apply(p, inputs))(model.params)


def predict(model: ModelState, actions: jax.Array, task: Task,
            features: bool = False) -> tuple[jax.Array, jax.Array]:
    """phi in real units, the members' mean: actions [..., n] -> behaviors [..., d], qualities [...]."""
    y = predict_members(model, actions, task, features).mean(axis=0)
    return y[..., :-1], y[..., -1]


def train(model: ModelState, key: jax.Array, data: Repertoire | Archive, task: Task, learning_rate: jax.Array,
          batch_size: int, num_batches: int, feature_rows: int | None = None,
          features: jax.Array | None = None, novelty_power: float = 0.0) -> tuple[ModelState, jax.Array]:
    """`num_batches` Adam steps at `learning_rate`, each member on its own mini-batches of `batch_size` rows.

    `data` is a repertoire (its valid rows are the prefix [0, count)) or a
    rollout buffer (`Archive`: the filled prefix [0, min(total, A))); it must
    hold at least one row. With `feature_rows` the inputs include the task's
    features of `feature_rows` rows drawn uniformly (with replacement) from the
    data, on which the steps then draw their mini-batches (features can cost a
    forward-kinematics pass per row: read from `features`, the data's rows'
    features where known, else computed for those rows). With `novelty_power`
    p > 0 (a repertoire only) the steps draw from a resample of it (`by_novelty`)
    in place of the repertoire itself. Returns the new state and the mean loss
    over the steps and members.
    """
    filled = data.count if isinstance(data, Repertoire) else jnp.minimum(data.total, data.qualities.shape[0])
    actions, targets = data.actions, normalize_targets(data.behaviors, data.qualities, task)
    if novelty_power:
        if not isinstance(data, Repertoire):
            raise ValueError(f"model.train: novelty_power={novelty_power!r} draws by the skills' novelty, which a "
                             "rollout buffer does not have: train on a repertoire or set novelty_power=0")
        key, drawn = jax.random.split(key)
        rows = by_novelty(drawn, data, novelty_power)
        actions, targets, filled = actions[rows], targets[rows], jnp.int32(rows.shape[0])
        features = None if features is None else features[rows]
    if feature_rows is None:
        return fit(model, key, normalize_actions(actions, task), targets, filled, learning_rate, batch_size,
                   num_batches)
    key, drawn = jax.random.split(key)
    rows = jax.random.randint(drawn, (feature_rows,), 0, filled)
    x = inputs(actions[rows], task, True) if features is None else inputs_with(actions[rows], features[rows], task)
    return fit(model, key, x, targets[rows], jnp.int32(feature_rows), learning_rate, batch_size, num_batches)


def by_novelty(key: jax.Array, rep: Repertoire, power: float) -> jax.Array:
    """[C] slots of a resample of the repertoire's skills, with replacement, each drawn with probability
    proportional to (novelty + 1e-6) ** power (a skill without neighbours can still be drawn): the training rows
    of `train(novelty_power=power)`, which then weigh skills by their novelty as the parents are drawn
    (`selection`), more steeply for power > 1. Where every weight underflows to 0, uniformly over the skills
    (`selection.probabilities`)."""
    p = selection.probabilities((rep.novelty + 1e-6) ** float(power), rep.valid)
    return jax.random.choice(key, rep.capacity, (rep.capacity,), p=p)


def fit(model: ModelState, key: jax.Array, inputs: jax.Array, targets: jax.Array, filled: jax.Array,
        learning_rate: jax.Array, batch_size: int, num_batches: int) -> tuple[ModelState, jax.Array]:
    """`train`'s steps on normalized inputs [R, n] and targets [R, out] whose first `filled` (>= 1) rows are data:
    mean-squared error, each member's rows drawn uniformly with replacement. Returns the new state and the mean
    loss over the steps and members."""
    import optax

    net, optimizer = _network_of(model), _optimizer()
    rows = jax.random.randint(key, (num_batches, ensemble_size(model), batch_size), 0, filled)

    def loss_fn(params: Any, idx: jax.Array) -> jax.Array:
        # Summed over members: each member's gradient is that of its own mean-squared error.
        member_loss = jax.vmap(lambda p, i: ((net.apply(p, inputs[i]) - targets[i]) ** 2).mean())
        return member_loss(params, idx).sum()

    def step(carry: tuple[Any, Any], idx: jax.Array) -> tuple[tuple[Any, Any], jax.Array]:
        params, opt_state = carry
        loss, grads = jax.value_and_grad(loss_fn)(params, idx)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), loss

    hyperparams = {**model.opt_state.hyperparams, "learning_rate": jnp.asarray(learning_rate, jnp.float32)}
    opt_state = model.opt_state._replace(hyperparams=hyperparams)
    (params, opt_state), losses = jax.lax.scan(step, (model.params, opt_state), rows, unroll=2)
    return (ModelState(params=params, opt_state=opt_state, steps=model.steps + num_batches),
            losses.mean() / ensemble_size(model))
