"""A user's own surrogate and rule: the model emitter keeps their contracts (docs/extending.md) for any of them.

The docs' kNN surrogate and random-share rule run through `run_mqd`, checkpoints and `adapt` in
test_docs.py; here, parts that record what the emitter does with them."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mqd_jax import Config, IsoLine, ModelEmitter, Params, run_mqd


@dataclasses.dataclass(frozen=True)
class Truthful:
    """Predicts the task's true outcomes; records each fit's repertoire count (its state sized by the capacity)."""

    def init(self, key, task, capacity):
        return {"fits": jnp.int32(0), "counts": jnp.full(capacity, -1, jnp.int32)}

    def fit(self, key, state, repertoire, task, params):
        counts = state["counts"].at[state["fits"]].set(repertoire.count)
        return {"fits": state["fits"] + 1, "counts": counts}, state["fits"].astype(jnp.float32)

    def predict(self, state, actions, task):
        behaviors, qualities, _ = task.evaluate(actions, None)
        return behaviors, qualities


@dataclasses.dataclass(frozen=True)
class Drawn:
    """Rolls out `num` rows of its pool drawn at random from its key, the last ones first; counts its updates."""

    def pool_size(self, num):
        return 3 * num

    def init(self, key, task):
        return jnp.int32(0)

    def select(self, key, state, judged, repertoire, wanted, params, num):
        rows = jax.random.choice(key, wanted.shape[0], (num,), replace=False)
        return rows, wanted[rows], jnp.int32(wanted.shape[0] - num)

    def update(self, key, state, proposal, evaluated):
        return state + 1


def test_any_surrogate_is_fitted_after_warm_up_on_the_repertoire_and_its_error_measured(tiny, linear_task):
    cfg = tiny(task=linear_task, algorithm=ModelEmitter(IsoLine(), Drawn(), Truthful(), warmup_samples=40),
               max_generations=6, population_size=16, capacity=64, archive_capacity=16)
    state, metrics = run_mqd(jax.random.PRNGKey(0), cfg)
    seen = np.asarray(metrics["num_evaluations"])
    fitted = seen >= 40  # the generations whose rollouts ended warm-up or came after it: 3rd to 6th
    assert int(state.emitter.surrogate["fits"]) == fitted.sum() == 4
    # Each fit saw the repertoire after that generation's insertions; the state is as big as the capacity.
    np.testing.assert_array_equal(state.emitter.surrogate["counts"][:4], np.asarray(metrics["repertoire_size"])[fitted])
    assert state.emitter.surrogate["counts"].shape == (cfg.capacity,)
    loss = np.asarray(metrics["model_loss"])
    assert np.isnan(loss[~fitted]).all() and (loss[fitted] == np.arange(4)).all()
    # The emitter's held-out error, for any surrogate: a truthful one's is 0.
    np.testing.assert_allclose(np.asarray(metrics["prediction_error"]), 0.0, atol=1e-12)
    assert int(state.emitter.acquisition) == cfg.max_generations  # the rule's state, updated every generation


def test_the_rule_draws_from_a_key_of_its_own_and_warm_up_is_the_emitters(linear_task):
    emitter = ModelEmitter(IsoLine(), Drawn(), Truthful(), warmup_samples=40)
    state = emitter.init(jax.random.PRNGKey(0), linear_task, 64)
    qd = Config(task=linear_task, algorithm="qd", population_size=16, max_generations=2, capacity=64,
                archive_capacity=16)
    rep = run_mqd(jax.random.PRNGKey(0), qd)[0].repertoire
    params = Params(jnp.float32(0.02), emitter.default_params())
    key = jax.random.PRNGKey(3)
    pool = IsoLine().propose(key, (), rep, linear_task, Params(jnp.float32(0.02), IsoLine().default_params()), 24)
    # Warm-up: the pool's first 8 rows as the inner emitter proposed them, whatever the rule would draw.
    warm = emitter.propose(key, state, rep, linear_task, params, 8)
    np.testing.assert_array_equal(warm.actions, pool.actions[:8])
    after = state.replace(evaluations=jnp.int32(40))
    drawn = [np.asarray(emitter.propose(k, after, rep, linear_task, params, 8).actions)
             for k in (key, key, jax.random.PRNGKey(4))]
    rows = [np.flatnonzero((np.asarray(pool.actions) == a).all(1))[0] for a in drawn[0]]
    assert len(set(rows)) == 8 and rows != list(range(8))  # distinct rows of the pool, drawn
    np.testing.assert_array_equal(drawn[0], drawn[1])  # the same key, the same draw
    assert not np.array_equal(drawn[0], drawn[2])


def test_a_surrogate_without_the_protocol_is_refused_with_what_it_lacks():
    with pytest.raises(ValueError, match=r"expected a surrogate, an object with init\(key, task, capacity\)"):
        ModelEmitter(IsoLine(), surrogate=Drawn())
