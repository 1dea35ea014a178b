import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from mqd_jax import Config, Task, run_mqd


@dataclasses.dataclass(frozen=True, eq=False)
class Reach(Task):
    """The README's example: a 2-link planar arm."""

    def evaluate(self, actions, key):
        a1, a2 = actions[:, 0], actions[:, 0] + actions[:, 1]
        tip = 0.5 + 0.25 * jnp.stack([jnp.cos(a1) + jnp.cos(a2), jnp.sin(a1) + jnp.sin(a2)], axis=1)
        return tip, -jnp.abs(actions).sum(1), jnp.ones(actions.shape[0], bool)


def test_registered_user_task_runs_and_stores_true_behaviors():
    envs.register("reach_test", lambda: Reach((-3.14, -3.14), (3.14, 3.14), (0.0, 0.0), (1.0, 1.0)))
    cfg = Config(task="reach_test", max_generations=10, population_size=16, capacity=256)
    state, m = run_mqd(jax.random.PRNGKey(0), cfg)
    n = int(state.repertoire.count)
    assert n > 16 and float(m["coverage"][-1]) > float(m["coverage"][0])
    rep = state.repertoire
    b, q, _ = envs.make("reach_test").evaluate(rep.actions[:n], None)
    np.testing.assert_allclose(rep.behaviors[:n], b, atol=1e-6)
    np.testing.assert_allclose(rep.qualities[:n], q, atol=1e-6)
    with pytest.raises(ValueError, match="already registered"):
        envs.register("reach_test", lambda: None)
