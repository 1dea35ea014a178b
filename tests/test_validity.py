"""The validity classifier (`mqd_jax.surrogate.validity`) and how the acquisition rules read it: hand-computed cases,
invariants against the run's own accounting (that a task without unusable rollouts runs exactly as without it:
test_programs_agree.py)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mqd_jax import Anchoring, IsoLine, ModelEmitter, Params, Steering, Surrogate, Task, Validity, run_mqd
from mqd_jax.emitters.acquisition import Budgeted, Judged, Threshold, ranking
from mqd_jax.emitters.diverse import Diverse
from mqd_jax.emitters.model_emitter import auc
from mqd_jax.emitters.pursuit import Fallback


@dataclasses.dataclass(frozen=True, eq=False)
class HalfUsable(Task):
    """Behavior and quality are affine maps of a 3D action; a rollout is usable where the first action is >= 0."""

    def evaluate(self, actions, key):
        b = 0.5 + 0.2 * jnp.stack([actions[:, 0] - actions[:, 1], actions[:, 2] + 0.5 * actions[:, 0]], axis=1)
        return b, 0.5 + 0.3 * actions[:, 1], actions[:, 0] >= 0


def half_usable():
    return HalfUsable((-1.0,) * 3, (1.0,) * 3, (0.0, 0.0), (1.0, 1.0))


def test_it_neither_trains_nor_judges_before_an_unusable_rollout_and_remembers_only_rolled_out_rows():
    task, validity = half_usable(), Validity(hidden_size=8, buffer_size=6, batch_size=4, num_batches=3)
    state = validity.init(jax.random.PRNGKey(0), task)
    actions = jnp.linspace(-1.0, 1.0, 15).reshape(5, 3)
    usable = jnp.ones(5, bool)
    state = validity.update(jax.random.PRNGKey(1), state, actions, jnp.array([1, 1, 0, 1, 1], bool), usable, task,
                            jnp.float32(1e-2))
    untrained = validity.init(jax.random.PRNGKey(0), task).model
    for a, b in zip(jax.tree.leaves(state.model), jax.tree.leaves(untrained), strict=True):
        np.testing.assert_array_equal(a, b)  # all usable so far: no step taken
    np.testing.assert_array_equal(validity.probability(state, actions, task), 1.0)
    assert int(state.buffer.total) == 4 and int(state.unusable) == 0
    np.testing.assert_array_equal(state.buffer.actions[:4], actions[jnp.array([0, 1, 3, 4])])
    # One unusable rollout (not rolled out rows are not remembered): now it trains, 3 steps.
    state = validity.update(jax.random.PRNGKey(2), state, actions[:3], jnp.array([0, 1, 1], bool),
                            jnp.array([True, False, True]), task, jnp.float32(1e-2))
    assert int(state.unusable) == 1 and int(state.buffer.total) == 6 and int(state.model.steps) == 3
    np.testing.assert_array_equal(state.buffer.qualities[4:], [0.0, 1.0])  # the labels, in order
    p = validity.probability(state, actions, task)
    assert np.all((p >= 0) & (p <= 1)) and not np.all(p == 1.0)


def test_it_learns_which_half_of_the_action_space_is_usable():
    task, validity = half_usable(), Validity(hidden_size=16, buffer_size=512, num_batches=200)
    state = validity.init(jax.random.PRNGKey(0), task)
    update = jax.jit(validity.update, static_argnums=5)
    for step in range(5):
        actions = jax.random.uniform(jax.random.PRNGKey(10 + step), (100, 3), minval=-1.0, maxval=1.0)
        state = update(jax.random.PRNGKey(step), state, actions, jnp.ones(100, bool), actions[:, 0] >= 0, task,
                       jnp.float32(1e-2))
    test = jax.random.uniform(jax.random.PRNGKey(99), (400, 3), minval=-1.0, maxval=1.0)
    p = np.asarray(validity.probability(state, test, task))
    clear = np.abs(np.asarray(test[:, 0])) > 0.3
    right = (p >= 0.5) == (np.asarray(test[:, 0]) >= 0)
    assert right[clear].mean() > 0.95
    assert float(auc(jnp.asarray(p), test[:, 0] >= 0, test[:, 0] < 0)) > 0.95


def test_the_rules_put_likely_unusable_candidates_after_the_others_by_hand():
    """Novelty [0.5, 0.3, 0.01, 0.02] with t_nov 0.04: 0 and 1 are novel; the validity judgement [0.2, 0.9, 0.9,
    0.1] puts 1 before 0 and 2 before 3; Threshold rolls out the novel one judged likely usable only."""
    novelty = jnp.array([0.5, 0.3, 0.01, 0.02])
    improvement = jnp.array([0.0, 0.0, 0.1, 0.2])
    wanted = jnp.ones(4, bool)
    np.testing.assert_array_equal(ranking(novelty, improvement, jnp.float32(0.04), wanted), [0, 1, 3, 2])
    validity = jnp.array([0.2, 0.9, 0.9, 0.1])
    pool = Judged(jnp.zeros((4, 2)), jnp.zeros(4), jnp.zeros(4), novelty, jnp.zeros(4), novelty, improvement,
                  novelty[:, None], validity)
    budgeted, threshold = Budgeted(1, t_nov=0.04), Threshold(t_nov=0.04, t_qua=0.15)
    key = jax.random.PRNGKey(0)
    rows, _, _ = budgeted.select(key, (), pool, None, wanted, Params(0.02, budgeted.default_params()), 4)
    np.testing.assert_array_equal(rows, [1, 0, 2, 3])
    _, rollout, discarded = threshold.select(key, (), pool, None, wanted, Params(0.02, threshold.default_params()), 4)
    np.testing.assert_array_equal(rollout, [False, True, False, False])  # 3 passes t_qua but is judged unusable
    assert int(discarded) == 3


def composed(validity):
    return ModelEmitter(IsoLine(), Diverse(3), Surrogate(num_batches=5, validity=validity), warmup_samples=32,
                        parts=(Steering(share=0.3), Anchoring("auto"), Fallback()))


def test_its_buffer_counts_every_rollout_the_run_counts(tiny):
    """On a task with an unusable half: the classifier remembers every rollout of the run, and as many unusable
    ones as the run's `invalid` metric counts; its AUC is a probability wherever both kinds were rolled out."""
    cfg = tiny(task=half_usable(), algorithm=composed(Validity(buffer_size=1024, num_batches=20)))
    state, m = run_mqd(jax.random.PRNGKey(0), cfg)
    validity = state.emitter.surrogate.validity
    assert int(validity.buffer.total) == int(np.sum(m["evaluations"]))
    assert int(validity.unusable) == int(np.sum(m["invalid"])) > 0
    labels = np.asarray(validity.buffer.qualities[:int(validity.buffer.total)])
    assert int((labels == 0).sum()) == int(validity.unusable)
    np.testing.assert_array_equal(labels == 1, np.asarray(validity.buffer.actions[:labels.size, 0]) >= 0)
    value = np.asarray(m["validity_auc"])
    both = (np.asarray(m["invalid"]) > 0) & (np.asarray(m["invalid"]) < np.asarray(m["evaluations"]))
    assert np.all((value[both] >= 0) & (value[both] <= 1)) and np.all(np.isnan(value[~both]))


@pytest.mark.parametrize("kw, field", [(dict(hidden_size=0), "hidden_size"), (dict(buffer_size=2.0), "buffer_size"),
                                       (dict(num_batches=True), "num_batches")])
def test_validity_is_validated(kw, field):
    with pytest.raises(ValueError, match=rf"Validity\.{field}="):
        Validity(**kw)
    with pytest.raises(ValueError, match=r"Surrogate\.validity="):
        Surrogate(validity=True)
