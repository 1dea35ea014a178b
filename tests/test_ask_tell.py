import jax
import jax.numpy as jnp
import pytest

from mqd_jax import ask, init, tell


def test_tell_refuses_results_of_the_wrong_shape(tiny):
    cfg = tiny()
    state = init(jax.random.PRNGKey(0), cfg)
    c = ask(state, cfg)
    pop = cfg.population_size
    good = (jnp.zeros((pop, 2)), jnp.zeros(pop), jnp.ones(pop, bool))
    for i, bad, msg in [(0, jnp.zeros((pop, 3)), r"behaviors has shape \(16, 3\); expected \(16, 2\)"),
                        (1, jnp.zeros(pop - 1), r"qualities has shape \(15,\); expected \(16,\)"),
                        (2, jnp.ones(pop), "valid has dtype float32; expected bool")]:
        args = list(good)
        args[i] = bad
        with pytest.raises(ValueError, match=msg):
            tell(state, c, *args, cfg)
