"""Curiosity: a skill's record of children that opened niches reweighs the candidates varied from it (hand-computed
records and factors, the chain's judge stage, the preset's option; a whole run's record: test_local.py)."""

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiled import compiled

from mqd_jax import Config, Curiosity, Diverse, Evaluated, IsoLine, ModelEmitter, Proposal, Surrogate, presets
from mqd_jax.core.emitter import init_emitter
from mqd_jax.core.repertoire import AddStatus, Repertoire
from mqd_jax.emitters import parts
from mqd_jax.experiment.migrations import upgraded

S = AddStatus


def _recorded(part):
    """A record of four slots after one generation of six rows (hand-counted in the test)."""
    parents = jnp.array([0, 0, 1, -1, 2, 0], jnp.int32)
    rollout = jnp.array([True, True, True, True, False, True])
    status = jnp.array([S.ADDED, S.REJECTED, S.ADDED, S.ADDED, S.SKIPPED, S.REPLACED], jnp.int32)
    proposal = Proposal(jnp.zeros((6, 2)), rollout, types.SimpleNamespace(parents=parents))
    evaluated = Evaluated(jnp.zeros((6, 2)), jnp.zeros(6), rollout, status)
    return part.update(part.init(None, None, 4), (), proposal, evaluated)


def test_the_record_and_its_factor_by_hand():
    state = _recorded(Curiosity(near=False))
    # Slot 0: three children rolled out, one opened; slot 1: one of one; slot 2's child was not rolled out; the
    # parentless row and the one not rolled out go to the last column, outside every record.
    np.testing.assert_array_equal(state, [[3, 1, 0, 0, 2], [1, 1, 0, 0, 1]])
    rep = Repertoire.empty(4, 2, 2, 2)
    parents = jnp.array([0, 1, 2, 3, -1])
    # The run's rate: (2 + 1/2) / (4 + 1) = 1/2; factor ((O / r + 4) / (T + 4)) ** weight.
    np.testing.assert_allclose(Curiosity(near=False).factor(state, parents, rep), [6 / 7, 6 / 5, 1, 1, 1], rtol=1e-6)
    np.testing.assert_allclose(Curiosity(weight=2.0, prior=1.0, near=False).factor(state, parents, rep),
                               [(3 / 4) ** 2, (3 / 2) ** 2, 1, 1, 1], rtol=1e-6)
    # With near, the records of the parent's listed neighbours count too: slot 2 lists 0, slot 0 lists 1 and 2.
    rep = rep.replace(neighbours=rep.neighbours.replace(index=jnp.array([[1, 2], [-1, -1], [0, -1], [-1, -1]])))
    np.testing.assert_allclose(Curiosity().factor(state, parents, rep), [1, 6 / 5, 6 / 7, 1, 1], rtol=1e-6)
    assert np.allclose(Curiosity(weight=0.0).factor(state, parents, rep), 1.0)


def test_the_judge_stage_reweighs_the_parents_novelty_as_the_rule_reads_it(linear_task):
    part = Curiosity(near=False)
    emitter = ModelEmitter(IsoLine(), Diverse(4, parent_weight=1.0), Surrogate(num_batches=1), warmup_samples=8,
                           parts=(part,))
    state = emitter.init(jax.random.PRNGKey(0), linear_task, 4)
    assert state.parts["curiosity"].shape == (2, 5)  # sized by the capacity
    state = state.replace(parts={"curiosity": _recorded(part)})
    rep = Repertoire.empty(4, 3, 2, 2)
    rep = rep.replace(valid=jnp.arange(4) < 3, count=jnp.int32(3), novelty=jnp.array([0.5, 2.0, 1.0, 0.0]))
    parents = jnp.array([0, 1, 2, -1], jnp.int32)
    judged = compiled(emitter.judge)(state, jnp.zeros((4, 3)), rep, linear_task, parents)
    np.testing.assert_allclose(judged.parent_novelty[:3], [0.5 * 6 / 7, 2.0 * 6 / 5, 1.0], rtol=1e-6)
    assert np.isnan(judged.parent_novelty[3])  # a candidate without a parent stays without
    # A pool that names no parents is left as it is.
    assert emitter.judge(state, jnp.zeros((4, 3)), rep, linear_task).parent_novelty is None


def test_the_presets_option_and_bad_settings():
    for algorithm in ("mqd", "mqd-local"):  # a config saved before 0.23 has no curiosity: it had none (its folder
        now = Config(algorithm=algorithm, algorithm_options={"pool_factor": 4}).to_dict()  # resumes as the same run)
        saved = {**now, "algorithm_options": {k: v for k, v in now["algorithm_options"].items() if k != "curiosity"}}
        assert upgraded(saved) == now
    chain = presets.mqd(curiosity=1.5).parts
    assert [p.name for p in chain] == ["steering", "anchoring", "curiosity", "fallback"]
    assert chain[2] == Curiosity(1.5)
    assert "curiosity" not in [p.name for p in presets.mqd().parts]
    assert presets.mqd_local(curiosity=1.0).parts[2] == Curiosity(1.0)
    with pytest.raises(ValueError, match="parent_weight=0 turns off"):
        presets.mqd(curiosity=1.0, parent_weight=0.0)
    with pytest.raises(ValueError, match=r"curiosity=-1 is invalid"):
        presets.mqd(curiosity=-1)
    for bad, match in (({"weight": -1.0}, "weight"), ({"prior": 0.0}, "prior"), ({"near": 1}, "near")):
        with pytest.raises(ValueError, match=rf"Curiosity\.{match}="):
            Curiosity(**bad)


def test_a_part_without_the_judge_stage_or_a_size_keeps_working():
    """A part that does not subclass `Part` and predates 0.23 has neither `judged` nor `sized`."""
    old = types.SimpleNamespace(name="old", init=lambda key, task: "state of (key, task)")
    assert init_emitter(old, None, None, 64) == "state of (key, task)"
    assert init_emitter(Curiosity(), None, None, 3).shape == (2, 4)
    judgement = object()
    assert parts.judged((old,), {"old": ()}, judgement, None) is judgement
