import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mqd_jax import Config, Task, run_mqd
from mqd_jax.core import registry
from mqd_jax.surrogate import model


@dataclasses.dataclass(frozen=True, eq=False)
class Reach(Task):
    """The README's example: a 2-link planar arm."""

    quality_range = (-6.3, 0.0)

    def evaluate(self, actions, key):
        a1, a2 = actions[:, 0], actions[:, 0] + actions[:, 1]
        tip = 0.5 + 0.25 * jnp.stack([jnp.cos(a1) + jnp.cos(a2), jnp.sin(a1) + jnp.sin(a2)], axis=1)
        return tip, -jnp.abs(actions).sum(1), jnp.ones(actions.shape[0], bool)


def test_registered_user_task_runs_and_stores_true_behaviors(registered):
    registered("reach_test", lambda: Reach((-3.14, -3.14), (3.14, 3.14), (0.0, 0.0), (1.0, 1.0)))
    cfg = Config(task="reach_test", max_generations=10, population_size=16, capacity=256)
    state, m = run_mqd(jax.random.PRNGKey(0), cfg)
    n = int(state.repertoire.count)
    assert n > 16 and float(m["coverage"][-1]) > float(m["coverage"][0])
    rep = state.repertoire
    b, q, _ = registry.make("reach_test").evaluate(rep.actions[:n], None)
    np.testing.assert_allclose(rep.behaviors[:n], b, atol=1e-6)
    np.testing.assert_allclose(rep.qualities[:n], q, atol=1e-6)
    with pytest.raises(ValueError, match="already registered"):
        registry.register("reach_test", lambda: None)


def test_mqd_on_a_user_task_learns_its_quality_range():
    task = Reach((-3.14, -3.14), (3.14, 3.14), (0.0, 0.0), (1.0, 1.0))
    cfg = Config(task=task, algorithm="mqd", max_generations=12, population_size=32, capacity=512,
                 algorithm_options=dict(warmup_samples=128, learning_rate=1e-2, num_batches=100))
    state, _ = run_mqd(jax.random.PRNGKey(0), cfg)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (256, 2), minval=-3.14, maxval=3.14)
    _, pred_q = model.predict(state.emitter.surrogate.model, actions, task)
    _, q, _ = task.evaluate(actions, None)
    # tanh outputs map onto quality_range, and the model has learnt where in it qualities lie.
    assert np.all((np.asarray(pred_q) >= -6.3) & (np.asarray(pred_q) <= 0.0))
    # Predicting the mean would give an RMS error of 1 std; a wrong quality normalization, far more.
    assert float(jnp.sqrt(jnp.mean((pred_q - q) ** 2))) < 0.25 * float(jnp.std(q))
