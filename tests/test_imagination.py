"""Imagination: QD run inside the model, only what it adds rolled out."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiled import compiled

from mqd_jax import Anchoring, Fallback, Imagination, IsoLine, ModelEmitter, Params, Steering, Surrogate, run_mqd
from mqd_jax.core import repertoire as repertoire_lib
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.emitters.imagination import survivors

T_DIST = 0.05
K = 3


@dataclasses.dataclass(frozen=True)
class _Perfect(Surrogate):
    """A model that knows the task's true outcomes."""

    def members(self, state, actions, task, inputs=None):
        b, q, _ = task.evaluate(actions, None)
        return jnp.concatenate([b, q[:, None]], axis=-1)[None]


def _insert(rep, actions, task, rollout):
    b, q, _ = task.evaluate(actions, None)
    return compiled(repertoire_lib.insert)(rep, actions, b, q, rollout, jnp.float32(T_DIST), K,
                                           repertoire_lib.NUM_NEAR, chunk=32)


def test_survivors_by_hand():
    c = 9  # capacity: "not in the repertoire"
    written = jnp.array([[0, 5, c], [5, 1, c], [2, c, 1]])
    # Generation 0's slot 5 and generation 1's slot 1 are written again later.
    np.testing.assert_array_equal(survivors(written, c), [[True, False, False], [True, False, False],
                                                          [True, False, True]])


def test_with_a_perfect_model_it_rolls_out_what_imagined_qd_keeps_by_brute_force(linear_task, tiny):
    start = jax.random.uniform(jax.random.PRNGKey(3), (12, 3), minval=-1.0, maxval=1.0)
    rep, _ = _insert(Repertoire.empty(64, 3, 2, K + 2), start, linear_task, jnp.ones(12, bool))
    emitter = ModelEmitter(IsoLine(), Imagination(generations=2), _Perfect(), k=K)
    params = Params(jnp.float32(T_DIST), emitter.default_params())
    state = compiled(emitter.init)(jax.random.PRNGKey(0), linear_task, 64)
    key, num = jax.random.PRNGKey(7), 10
    proposal = compiled(emitter.propose)(key, state, rep, linear_task, params, num)
    params = params.part(params.emitter.inner)  # IsoLine's, as the emitter hands them to it

    # Two QD generations by hand on the true outcomes; a candidate survives if it is alive after its generation
    # and the next generation does not write its slot.
    k0, k1 = jax.random.split(key, 2)
    pool0 = compiled(IsoLine().propose)(k0, (), rep, linear_task, params, num)
    rep1, ins0 = _insert(rep, pool0.actions, linear_task, pool0.rollout)
    pool1 = compiled(IsoLine().propose)(k1, (), rep1, linear_task, params, num)
    _, ins1 = _insert(rep1, pool1.actions, linear_task, pool1.rollout)
    later = {int(s) for s, a in zip(ins1.slot, ins1.alive, strict=True) if a}
    keep0 = [bool(a) and int(s) not in later for s, a in zip(ins0.slot, ins0.alive, strict=True)]
    keep1 = [bool(a) for a in ins1.alive]
    actions = np.concatenate([pool0.actions, pool1.actions])
    keep = np.array(keep0 + keep1)
    order = [i for i in range(2 * num) if keep[i]] + [i for i in range(2 * num) if not keep[i]]
    assert 0 < keep.sum() < 2 * num  # the case tests both kinds
    np.testing.assert_allclose(proposal.actions, actions[order[:num]], rtol=1e-5, atol=1e-6)  # jit vs eager
    np.testing.assert_array_equal(proposal.rollout, keep[order[:num]])
    assert int(proposal.info.discarded) == num - int(keep[order[:num]].sum())


def test_during_warm_up_it_rolls_out_the_inner_emitters_first_candidates(linear_task, tiny):
    rep, _ = _insert(Repertoire.empty(64, 3, 2, K + 2), jnp.zeros((1, 3)), linear_task, jnp.ones(1, bool))
    emitter = ModelEmitter(IsoLine(), Imagination(generations=3), _Perfect(), k=K, warmup_samples=100)
    params = Params(jnp.float32(0.02), emitter.default_params())
    key = jax.random.PRNGKey(5)
    proposal = compiled(emitter.propose)(key, compiled(emitter.init)(key, linear_task, 64), rep, linear_task, params, 6)
    first = compiled(IsoLine().propose)(jax.random.split(key, 3)[0], (), rep, linear_task,
                                        params.part(params.emitter.inner), 6)
    np.testing.assert_allclose(proposal.actions, first.actions, rtol=1e-5, atol=1e-6)
    assert bool(proposal.rollout.all())


@pytest.mark.parametrize("generations", [0, 2.0])
def test_imagination_is_validated(generations):
    with pytest.raises(ValueError, match=r"Imagination\.generations="):
        Imagination(generations)


@pytest.mark.parametrize("part, why", [(Fallback(), "needs a ranking acquisition rule"),
                                       (Steering(), "needs a ranking acquisition rule")])
def test_a_part_that_needs_the_pool_or_a_ranking_is_refused_with_imagination(part, why):
    """Its rows are not a ranking (a share), and it draws its own pools (steering), both named."""
    with pytest.raises(ValueError, match=f"{type(part).__name__}.*{why}"):
        ModelEmitter(IsoLine(), Imagination(), parts=(part,))


def test_a_run_rolls_out_at_most_the_population_and_counts_the_rest_as_discarded(tiny):
    cfg = tiny(task="obstacle2d", algorithm=ModelEmitter(IsoLine(), Imagination(), Surrogate(num_batches=2),
                                                         warmup_samples=16, parts=(Anchoring("auto"),)))
    _, metrics = run_mqd(jax.random.PRNGKey(0), cfg)
    assert np.all(metrics["evaluations"] + metrics["discarded"] == cfg.population_size)
    assert metrics["evaluations"][0] == cfg.population_size  # warm-up: the first 16 rollouts
