"""Stepping aside: a model emitter whose model predicts no better than chance rolls out the inner emitter's own
candidates (`StepAside`)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiled import compiled

from mqd_jax import Diverse, Evaluated, IsoLine, ModelEmitter, Params, Surrogate, Task, Threshold, run_mqd
from mqd_jax.emitters.step_aside import StepAside, StepAsideState, explained


@dataclasses.dataclass(frozen=True, eq=False)
class Hashed(Task):
    """Behaviors that no model can predict: a hash of the action, uniform in the box."""

    def evaluate(self, actions, key):
        w = jnp.array([[12.9898, 78.233], [39.346, 11.135], [73.156, 52.235]])
        return jnp.mod(jnp.sin(actions @ w) * 43758.5453, 1.0), 0.5 + 0.0 * actions[:, 0], \
            jnp.ones(actions.shape[0], bool)


def test_the_skill_is_an_average_of_the_explained_variance_by_hand():
    b = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [9.0, 9.0]])
    usable = jnp.array([True, True, True, False])
    evaluated = Evaluated(b, jnp.zeros(4), usable, jnp.zeros(4, jnp.int32))
    # Mean (1/3, 1/3): spread 2/9 * 3 + ... = 4/3; predicting the mean explains 0, the truth 1.
    assert float(explained(jnp.full((4, 2), 1 / 3), evaluated)) == pytest.approx(0.0, abs=1e-6)
    assert float(explained(b, evaluated)) == pytest.approx(1.0)
    off = b.at[0].set(jnp.array([1.0, 1.0]))  # one row off by 2 in squares: 1 - 2 / (4/3)
    assert float(explained(off, evaluated)) == pytest.approx(-0.5)
    assert np.isnan(float(explained(b, evaluated.replace(usable=jnp.array([True, False, False, False])))))
    rule = StepAside(margin=0.1, rate=0.5)
    state = rule.init()
    assert bool(rule.trusts(state))  # nothing measured yet
    state = rule.averaged(state, jnp.float32(jnp.nan))
    assert np.isnan(float(state.skill))  # a generation without a measure changes nothing
    state = rule.averaged(state, jnp.float32(0.9))
    assert float(state.skill) == pytest.approx(0.9) and bool(rule.trusts(state))
    state = rule.averaged(state, jnp.float32(-0.5))
    assert float(state.skill) == pytest.approx(0.2) and bool(rule.trusts(state))
    state = rule.averaged(state, jnp.float32(-0.1))
    assert float(state.skill) == pytest.approx(0.05) and not bool(rule.trusts(state))
    with pytest.raises(ValueError, match=r"StepAside\.margin=2 is invalid"):
        StepAside(margin=2)
    with pytest.raises(ValueError, match=r"StepAside\(.*\) needs a ranking acquisition rule"):
        ModelEmitter(IsoLine(), Threshold(), parts=(StepAside(),))


def test_a_model_at_chance_rolls_out_the_inner_emitters_first_candidates(linear_task):
    emitter = ModelEmitter(IsoLine(), Diverse(4), Surrogate(num_batches=2), parts=(StepAside(),))
    state = compiled(emitter.init)(jax.random.PRNGKey(0), linear_task, 64)
    key, params = jax.random.PRNGKey(1), Params(jnp.float32(0.02), emitter.default_params())
    actions = jax.random.uniform(jax.random.PRNGKey(2), (20, 3), minval=-1.0, maxval=1.0)
    rep = _skills(linear_task, actions)
    pool = compiled(IsoLine().propose)(key, (), rep, linear_task, Params(jnp.float32(0.02), IsoLine().default_params()),
                                       32)
    propose = compiled(emitter.propose)
    at_chance = propose(key, state.replace(parts={"step_aside": StepAsideState(jnp.float32(0.02))}), rep, linear_task,
                        params, 8)
    np.testing.assert_array_equal(at_chance.actions, pool.actions[:8])
    assert not np.asarray(at_chance.info.from_model).any()
    skilled = propose(key, state.replace(parts={"step_aside": StepAsideState(jnp.float32(0.8))}), rep, linear_task,
                      params, 8)
    assert np.asarray(skilled.info.from_model).all()
    assert not np.array_equal(skilled.actions, pool.actions[:8])  # the rule's choice


def _skills(task, actions):
    from mqd_jax.core.repertoire import Repertoire

    b, q, _ = task.evaluate(actions, None)
    rep = Repertoire.empty(64, 3, 2, 4)
    n = actions.shape[0]
    return rep.replace(actions=rep.actions.at[:n].set(actions), behaviors=rep.behaviors.at[:n].set(b),
                       qualities=rep.qualities.at[:n].set(q), valid=jnp.arange(64) < n, count=jnp.int32(n),
                       novelty=rep.novelty.at[:n].set(1.0))


def test_on_a_task_no_model_can_predict_the_emitter_steps_aside(tiny):
    task = Hashed((-1.0,) * 3, (1.0,) * 3, (0.0, 0.0), (1.0, 1.0))
    emitter = ModelEmitter(IsoLine(), Diverse(4), Surrogate(num_batches=20), warmup_samples=64,
                           parts=(StepAside(),))
    _, m = run_mqd(jax.random.PRNGKey(0), tiny(task=task, algorithm=emitter, population_size=32,
                                                max_generations=16, t_dist=0.05))
    skill, share = np.asarray(m["model_skill"]), np.asarray(m["model_share"])
    aside = skill < 0.1
    # Each generation follows the skill it was chosen with: none of the rule's rows below 0.1, all of them else.
    np.testing.assert_array_equal(share[aside], 0.0)
    np.testing.assert_array_equal(share[~aside], 1.0)
    warm = np.isnan(skill)
    assert aside[~warm].all() and (~warm).sum() >= 10, skill  # no skill at a hash: aside from the first measure
