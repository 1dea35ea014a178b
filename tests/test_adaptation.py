import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mqd_jax import Config, adapt, adaptation, init, run_mqd
from mqd_jax.adaptation import METHODS
from mqd_jax.core import registry
from mqd_jax.surrogate import model


@pytest.fixture(scope="module")
def linear_cfg(linear_task):
    # Goals whose nearest skill is 0.02-0.1 away, well inside the linear task's reach.
    return Config(task=linear_task, algorithm="mqd", t_dist=1e-4,
                  algorithm_options=dict(warmup_samples=10, learning_rate=1e-2, num_batches=1000))


@pytest.fixture(scope="module")
def linear_state(linear_cfg, linear_task):
    """A repertoire of 64 skills spread over the linear task, and a model trained on them."""
    state = init(jax.random.PRNGKey(0), linear_cfg)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (64, 3), minval=-0.5, maxval=0.5)
    b, q, _ = linear_task.evaluate(actions, None)
    rep = state.repertoire
    n = 64
    rep = rep.replace(actions=rep.actions.at[:n].set(actions), behaviors=rep.behaviors.at[:n].set(b),
                      qualities=rep.qualities.at[:n].set(q), valid=jnp.arange(rep.capacity) < n, count=jnp.int32(n))
    trained, _ = model.train(state.emitter.surrogate.model, jax.random.PRNGKey(2), rep, linear_task, jnp.float32(1e-2),
                             linear_cfg.emitter.surrogate.batch_size, linear_cfg.emitter.surrogate.num_batches)
    return state.replace(repertoire=rep, emitter=state.emitter.replace(
        surrogate=state.emitter.surrogate.replace(model=trained), evaluations=jnp.int32(n)))


def goals_near(state, num=32):
    rep = state.repertoire
    offset = jax.random.uniform(jax.random.PRNGKey(5), (num, 2), minval=-0.07, maxval=0.07)
    return rep.behaviors[jnp.arange(num) % int(rep.count)] + offset


def test_nearest_is_the_nearest_skill(linear_state, linear_cfg):
    goals = goals_near(linear_state)
    out = adapt(linear_state, goals, jax.random.PRNGKey(0), linear_cfg, "nearest")
    rep = linear_state.repertoire
    b = np.asarray(rep.behaviors[:int(rep.count)])
    brute = np.argmin(((np.asarray(goals)[:, None] - b[None]) ** 2).sum(-1), axis=1)
    np.testing.assert_array_equal(out.actions, rep.actions[brute])
    np.testing.assert_allclose(out.errors, np.linalg.norm(np.asarray(goals) - b[brute], axis=1), rtol=1e-6)
    np.testing.assert_array_equal(out.steps, 0)
    np.testing.assert_array_equal(out.evaluations, 0)


def test_linear_method_contracts_the_error_exactly_on_a_linear_task(linear_state, linear_cfg):
    # The map is affine and K = 5 >= n = 3, so J is exact and each step scales the error by 1 - lambda.
    goals = goals_near(linear_state)
    start = adapt(linear_state, goals, jax.random.PRNGKey(0), linear_cfg, "nearest").errors
    for steps in (1, 3, 5):
        out = adapt(linear_state, goals, jax.random.PRNGKey(0), linear_cfg, "linear", steps=steps)
        np.testing.assert_allclose(out.errors, 0.9 ** steps * np.asarray(start), rtol=2e-3, atol=1e-6)
        np.testing.assert_array_equal(out.steps, steps)
        np.testing.assert_array_equal(out.evaluations, steps)


@pytest.mark.parametrize("method", ["linear", "model"])
def test_full_steps_reach_the_goal_and_stop(linear_state, method, linear_cfg, linear_task):
    t_dist = 0.005
    goals = goals_near(linear_state)
    out = adapt(linear_state, goals, jax.random.PRNGKey(0), linear_cfg, method, step_size=1.0, steps=10, t_dist=t_dist)
    assert np.all(np.asarray(out.errors) < t_dist)
    # Stopping rule: a step only while the error is >= t_dist; exact J needs one, the model a few.
    far = np.asarray(adapt(linear_state, goals, jax.random.PRNGKey(0), linear_cfg, "nearest").errors) >= t_dist
    assert far.sum() > 20
    steps = np.asarray(out.steps)
    np.testing.assert_array_equal(steps[~far], 0)
    assert np.all(steps[far] >= 1) and np.all(steps[far] <= (1 if method == "linear" else 4))
    b, _, _ = linear_task.evaluate(out.actions, None)
    np.testing.assert_allclose(out.behaviors, b, atol=1e-6)


def test_model_method_follows_the_linear_contraction_with_small_steps(linear_state, linear_cfg):
    goals = goals_near(linear_state)
    start = np.asarray(adapt(linear_state, goals, jax.random.PRNGKey(0), linear_cfg, "nearest").errors)
    errors = [np.asarray(adapt(linear_state, goals, jax.random.PRNGKey(0), linear_cfg, "model", steps=s).errors)
              for s in (1, 2, 3, 4, 5)]
    last = start
    for s, e in enumerate(errors, 1):
        assert np.all(e < last)  # strictly decreasing at every step, for every goal
        # A learned J is close to the true one: never much slower than the exact 0.9^s contraction,
        # and as fast on average.
        assert np.all(e <= 1.25 * 0.9 ** s * start + 1e-3)
        assert np.mean(e / start) == pytest.approx(0.9 ** s, rel=0.03)
        last = e


def test_goals_at_skills_take_no_step(linear_state, linear_cfg):
    goals = linear_state.repertoire.behaviors[:8]
    for method in METHODS:
        out = adapt(linear_state, goals, jax.random.PRNGKey(0), linear_cfg, method)
        np.testing.assert_array_equal(out.steps, 0)
        np.testing.assert_array_equal(out.actions, linear_state.repertoire.actions[:8])


@pytest.fixture(scope="module")
def obstacle_run(tiny):
    cfg = tiny(task="obstacle2d", algorithm="mqd", max_generations=10, population_size=32, warmup_samples=128,
               num_batches=100)
    state, _ = run_mqd(jax.random.PRNGKey(0), cfg)
    return state, cfg


def test_far_goals_give_finite_results_within_bounds(obstacle_run):
    state, cfg = obstacle_run
    goals = jnp.array([[10.0, -10.0], [-3.0, 0.5], [0.5, 100.0], [0.5, 0.5]])
    task = registry.make("obstacle2d")
    low, high = np.asarray(task.action_low), np.asarray(task.action_high)
    nearest = adapt(state, goals, jax.random.PRNGKey(0), cfg, "nearest")
    for method in METHODS:
        out = adapt(state, goals, jax.random.PRNGKey(1), cfg, method)
        for leaf in jax.tree.leaves(out):
            assert np.all(np.isfinite(np.asarray(leaf)))
        a = np.asarray(out.actions)
        assert np.all((a >= low) & (a <= high))
        assert np.all(np.asarray(out.errors) <= np.asarray(nearest.errors))  # the best iterate is kept
        assert np.all(np.asarray(out.steps) <= adaptation.STEPS)
        b, _, _ = task.evaluate(out.actions, None)
        np.testing.assert_allclose(out.behaviors, b, atol=1e-6)


def test_bad_calls_are_refused_before_tracing(obstacle_run):
    state, cfg = obstacle_run
    key = jax.random.PRNGKey(0)
    with pytest.raises(ValueError, match="method='gradient' is invalid"):
        adapt(state, jnp.zeros((3, 2)), key, cfg, "gradient")
    with pytest.raises(ValueError, match=r"goals has shape \(3, 3\): expected \(G, 2\)"):
        adapt(state, jnp.zeros((3, 3)), key, cfg, "linear")
    with pytest.raises(ValueError, match="repertoire is empty"):
        adapt(init(key, cfg), jnp.zeros((3, 2)), key, cfg, "linear")
    qd_cfg = dataclasses.replace(cfg, algorithm="qd", algorithm_options={})
    qd_state, _ = run_mqd(key, qd_cfg)
    with pytest.raises(ValueError, match="needs a run whose emitter has a model"):
        adapt(qd_state, jnp.zeros((3, 2)), key, qd_cfg, "model")
    with pytest.raises(ValueError, match=r"does not belong to this config.*another structure"):
        adapt(qd_state, jnp.zeros((3, 2)), key, cfg, "linear")  # a QD state with an M-QD config
    # A state whose run has not finished warm-up: its model never trained.
    untrained = state.replace(emitter=state.emitter.replace(evaluations=jnp.int32(cfg.options["warmup_samples"] - 1)))
    with pytest.raises(ValueError, match="needs a trained model"):
        adapt(untrained, jnp.zeros((3, 2)), key, cfg, "model")
