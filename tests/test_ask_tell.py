import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mqd_jax import ask, init, run_mqd, tell
from mqd_jax.core import registry


def numpy_evaluator(actions, mask):
    """A plain-numpy evaluator, as a robot's would be: rolls out only the masked rows."""
    actions = np.asarray(actions)
    task = registry.make("obstacle2d")
    b = np.zeros((len(actions), 2), np.float32)
    q = np.zeros(len(actions), np.float32)
    rows = np.flatnonzero(np.asarray(mask))
    if len(rows):
        b[rows], q[rows], _ = task.evaluate(actions[rows])  # numpy in, numpy out
    return b, q, np.asarray(mask).copy()


@pytest.mark.fusion_emitters
@pytest.mark.parametrize("algorithm", ["qd", "mqd"])
def test_ask_tell_with_a_numpy_evaluator_equals_the_fused_run(algorithm, tiny):
    cfg = tiny(task="obstacle2d", algorithm=algorithm, warmup_samples=64, num_batches=20)
    key = jax.random.PRNGKey(7)
    state = init(key, cfg)
    history = []
    for _ in range(cfg.max_generations):
        candidates = ask(state, cfg)
        b, q, valid = numpy_evaluator(candidates.actions, candidates.rollout)
        state, m = tell(state, candidates, b, q, valid, cfg)
        history.append(m)
    want_state, want = run_mqd(key, cfg)
    assert int(state.repertoire.count) == int(want_state.repertoire.count)
    rep, ref = state.repertoire, want_state.repertoire
    np.testing.assert_array_equal(rep.valid, ref.valid)
    # numpy and XLA may round the rollouts' last bits differently; every decision is the same.
    np.testing.assert_allclose(rep.actions, ref.actions, atol=1e-5)
    np.testing.assert_allclose(rep.behaviors, ref.behaviors, atol=1e-5)
    np.testing.assert_allclose(rep.qualities, ref.qualities, atol=1e-5)
    counts = ("added", "replaced", "rejected", "evaluations", "discarded", "num_evaluations")
    for name in (n for n in counts if n in want):  # "discarded": M-QD's model emitter only
        np.testing.assert_array_equal([int(m[name]) for m in history], want[name], err_msg=name)
    np.testing.assert_array_equal(state.key, want_state.key)


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
