"""The local surrogate (`mqd_jax.surrogate.local`): its fit against a brute-force weighted least squares, exact on an
affine map, differentiable, fed every rollout through the protocol's `observe`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiled import compiled

from mqd_jax import Config, run_mqd
from mqd_jax.core.emitter import Evaluated
from mqd_jax.core.state import get_task
from mqd_jax.emitters import presets
from mqd_jax.surrogate import protocol
from mqd_jax.surrogate.local import LocalLinear, spd_solve

TASK = get_task(Config(task="obstacle2d"))  # actions n = 9, behaviors d = 2


def _actions(key, num):
    low, high = np.asarray(TASK.action_low), np.asarray(TASK.action_high)
    return np.asarray(jax.random.uniform(jax.random.PRNGKey(key), (num, TASK.action_dim))) * (high - low) + low


def _fed(model, actions, outcomes, usable=None):
    """The model's state after observing rollouts of actions [P, n] with outcomes [P, d + 1]."""
    usable = np.ones(len(actions), bool) if usable is None else usable
    evaluated = Evaluated(jnp.asarray(outcomes[:, :2], jnp.float32), jnp.asarray(outcomes[:, 2], jnp.float32),
                          jnp.asarray(usable), None, None)
    state = compiled(model.init)(jax.random.PRNGKey(0), TASK, 16)
    return compiled(model.observe)(None, state, jnp.asarray(actions, jnp.float32), jnp.asarray(usable), evaluated,
                                   TASK, ())


def _brute_force(model, actions, outcomes, at):
    """The same fit written directly: k nearest by sorting, tricube weights, ridge on the slopes, numpy's solve."""
    low, high = np.asarray(TASK.action_low), np.asarray(TASK.action_high)
    unit = lambda a: 2 * (a - low) / (high - low) - 1  # noqa: E731
    xs, x = unit(actions), unit(at)
    k = model.neighbours or 4 * (TASK.action_dim + 1)
    nearest = np.argsort(((xs - x) ** 2).sum(1))[:k]
    z = np.hstack([np.ones((k, 1)), xs[nearest] - x])
    r = np.linalg.norm(xs[nearest] - x, axis=1)
    w = np.clip(1 - (r / (r.max() * np.sqrt(1.002))) ** 3, 0, 1) ** 3
    penalty = np.diag([1e-6 * model.ridge] + [model.ridge] * TASK.action_dim)
    return np.linalg.solve(z.T @ (w[:, None] * z) + penalty, z.T @ (w[:, None] * outcomes[nearest]))[0]


def test_a_prediction_is_the_weighted_least_squares_fit_to_the_nearest_rollouts():
    actions = _actions(0, 300)
    outcomes = np.stack([np.sin(3 * actions[:, 0]) + actions[:, 4], np.cos(actions[:, 1] * actions[:, 2]),
                         actions[:, 3] ** 2], axis=1)
    at = actions[:6] + 0.03  # children near some of the rollouts
    for model in (LocalLinear(buffer=512), LocalLinear(neighbours=12, ridge=0.1, buffer=512)):
        behaviors, qualities = compiled(model.predict)(_fed(model, actions, outcomes), jnp.asarray(at, jnp.float32),
                                                       TASK)
        got = np.concatenate([np.asarray(behaviors), np.asarray(qualities)[:, None]], axis=1)
        want = np.stack([_brute_force(model, actions, outcomes, a) for a in at])
        np.testing.assert_allclose(got, want, rtol=2e-3, atol=2e-4)


def test_an_affine_map_is_recovered_with_its_jacobian_and_only_usable_rollouts_are_kept():
    actions, slope = _actions(1, 200), np.asarray(jax.random.normal(jax.random.PRNGKey(2), (TASK.action_dim, 3)))
    outcomes = actions @ slope + np.array([0.3, -0.2, 0.5])
    usable = np.arange(200) % 4 != 0
    broken = np.where(usable[:, None], outcomes, 1e3)  # not usable: must not be read
    model = LocalLinear(ridge=1e-6, buffer=256)
    state = _fed(model, actions, broken, usable)
    assert int(state.total) == usable.sum()
    at = jnp.asarray(actions[1:4] + 0.01, jnp.float32)
    behaviors, qualities = compiled(model.predict)(state, at, TASK)
    np.testing.assert_allclose(np.asarray(behaviors), np.asarray(at) @ slope[:, :2] + [0.3, -0.2], atol=2e-3)
    np.testing.assert_allclose(np.asarray(qualities), np.asarray(at) @ slope[:, 2] + 0.5, atol=2e-3)
    # differentiable in the action, also at a rollout's own action (distance 0)
    for a in (at[0], jnp.asarray(actions[1], jnp.float32)):
        jacobian = compiled(jax.jacfwd(lambda x, state: model.predict(state, x, TASK)[0]))(a, state)
        np.testing.assert_allclose(np.asarray(jacobian), slope[:, :2].T, atol=2e-2)


def test_the_elimination_solves_symmetric_positive_definite_systems():
    a = np.asarray(jax.random.normal(jax.random.PRNGKey(3), (5, 7, 7)))
    a = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(7)
    b = np.asarray(jax.random.normal(jax.random.PRNGKey(4), (5, 7, 3)))
    np.testing.assert_allclose(np.asarray(spd_solve(jnp.asarray(a), jnp.asarray(b))), np.linalg.solve(a, b),
                               rtol=1e-3, atol=1e-4)


def test_in_mqd_it_observes_every_generation_s_rollouts_and_a_broken_observe_is_named():
    emitter = presets.mqd(surrogate=LocalLinear(buffer=64), warmup_samples=16, steering_share=0, curiosity=1.0)
    cfg = Config.paper_2d(task="obstacle2d", algorithm=emitter, population_size=8, max_generations=5, capacity=64,
                          archive_capacity=16)
    state, metrics = run_mqd(jax.random.PRNGKey(0), cfg)
    rolled = int(metrics["num_evaluations"][-1]) - int(metrics["invalid"].sum())
    assert int(state.emitter.surrogate.total) == rolled > 16  # through warm-up and after (not only the skills)
    # So does the same run's `Curiosity` (test_curiosity.py): its record counts every row once, every opener once.
    record = np.asarray(state.emitter.parts["curiosity"])
    assert record.shape == (2, cfg.capacity + 1) and record[0].sum() == 8 * 5
    assert record[1].sum() == np.asarray(metrics["added"]).sum() and (record[1] <= record[0]).all()
    assert record[0, -1] >= 8 and record[1, :-1].sum() > 0  # the first generation has no parents, the later ones

    class Reshaping(LocalLinear):
        def observe(self, key, state, *args, **kwargs):
            return state.replace(qualities=state.qualities[:-1])

    with pytest.raises(ValueError, match=r"^Reshaping.observe returned a state .*expected one of the structure"):
        _fed(protocol.hooks(Reshaping(buffer=64)), _actions(0, 8), np.zeros((8, 3)))


@pytest.mark.parametrize(("options", "message"), [
    ({"neighbours": 1}, "LocalLinear.neighbours=1 is invalid"), ({"ridge": 0.0}, "LocalLinear.ridge=0.0 is invalid"),
    ({"buffer": 1.5}, "LocalLinear.buffer=1.5 is invalid")])
def test_bad_options_are_refused(options, message):
    with pytest.raises(ValueError, match=message):
        LocalLinear(**options)


def test_the_named_preset_is_mqd_with_the_local_surrogate_and_a_saved_config_rebuilds_it():
    cfg = Config.paper("push_cube", algorithm="mqd-local", algorithm_options={"neighbours": 32, "pool_factor": 4})
    assert cfg.emitter == presets.mqd(surrogate=LocalLinear(neighbours=32), pool_factor=4)
    assert Config.paper("obstacle2d", algorithm="mqd-local").emitter == presets.mqd(surrogate=LocalLinear())
    assert Config.from_dict(cfg.to_dict()) == cfg  # a part given in Python could not be rebuilt from a file
    with pytest.raises(ValueError, match=r"mqd-local: neighbours=1 is invalid: expected 0 \(4 \(n \+ 1\)\)"):
        Config.paper("obstacle2d", algorithm="mqd-local", algorithm_options={"neighbours": 1})
    with pytest.raises(ValueError, match="hidden_size"):  # the network's options are not the preset's
        Config.paper("obstacle2d", algorithm="mqd-local", algorithm_options={"hidden_size": 64})
