"""Emitters side by side: each proposes its share of a generation, sees its own rows, and reports prefixed."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiled import compiled

from mqd_jax import (
    Emitter,
    Fallback,
    IsoLine,
    Params,
    SideBySide,
    Uniform,
    adapt,
    presets,
    run_mqd,
)
from mqd_jax.core.repertoire import AddStatus, Repertoire
from mqd_jax.core.state import get_task


@dataclasses.dataclass(frozen=True)
class Counting(Emitter):
    """Uniform candidates; reports how many of its rows were rolled out (status not SKIPPED) and the sum of their
    first action coordinate, as its update sees them."""

    def propose(self, key, state, repertoire, task, params, num):
        return Uniform().propose(key, state, repertoire, task, params, num)

    def update(self, key, state, proposal, evaluated, repertoire, task, params):
        seen = evaluated.status != AddStatus.SKIPPED
        return state, {"seen": seen.sum(dtype=jnp.int32),
                       "first": jnp.where(seen & proposal.rollout, proposal.actions[:, 0], 0.0).sum()}

    def metrics(self):
        return {"seen": jnp.int32, "first": jnp.float32}


def test_fixed_shares_concatenate_the_members_proposals_by_hand(linear_task):
    emitter = SideBySide((Uniform(), IsoLine()), shares=(0.25, 0.75))
    rep = Repertoire.empty(32, 3, 2, 4)
    params = Params(jnp.float32(0.02), emitter.default_params())
    key, state = jax.random.PRNGKey(3), compiled(emitter.init)(jax.random.PRNGKey(0), linear_task, 32)
    got = compiled(emitter.propose)(key, state, rep, linear_task, params, 12)
    first = compiled(Uniform().propose)(jax.random.fold_in(key, 0), (), rep, linear_task, params.part(()), 3)
    second = compiled(IsoLine().propose)(jax.random.fold_in(key, 1), (), rep, linear_task,
                                         params.part(params.emitter[1]), 9)
    np.testing.assert_array_equal(got.actions, np.concatenate([first.actions, second.actions]))
    np.testing.assert_array_equal(got.rollout, np.concatenate([first.rollout, second.rollout]))
    assert emitter.counts(12) == (3, 9) and emitter.pool_size(12) == 12


def test_each_member_sees_its_own_rows_and_reports_prefixed(tiny):
    cfg = tiny(algorithm=SideBySide((Counting(), Counting()), shares=(0.25, 0.75), names=("a", "b")),
               max_generations=3)
    _, m = run_mqd(jax.random.PRNGKey(0), cfg)
    assert {"a.seen", "b.seen", "a.first", "b.first"} <= set(m)
    np.testing.assert_array_equal(m["a.seen"], 4)
    np.testing.assert_array_equal(m["b.seen"], 12)


def test_an_adaptive_share_gives_the_first_member_its_first_rows(tiny):
    """With a share (pursuit), the generation holds round(share x num) of the first member's rows, then the
    second's: each member's update sees exactly those as rolled out; the share starts at 1/2."""
    cfg = tiny(algorithm=SideBySide((Counting(), Counting()), shares=Fallback(rate=0.5), names=("a", "b")),
               max_generations=6)
    _, m = run_mqd(jax.random.PRNGKey(1), cfg)
    share = np.asarray(m["share"])
    assert share[0] == 0.5
    np.testing.assert_array_equal(m["a.seen"], np.round(share * 16))
    np.testing.assert_array_equal(m["a.seen"] + m["b.seen"], 16)


def test_a_side_by_side_with_a_model_adapts_with_it(tiny):
    model = presets.mqd(warmup_samples=16, num_batches=2, pool_factor=4)
    cfg = tiny(task="obstacle2d", algorithm=SideBySide((presets.qd(), model)), max_generations=4)
    state, m = run_mqd(jax.random.PRNGKey(0), cfg)
    assert "modelemitter.discarded" in m and "isoline.discarded" not in m
    goals = jnp.array([[0.3, 0.6], [0.7, 0.2]])
    adapted = adapt(state, goals, jax.random.PRNGKey(2), cfg, "model", steps=3)
    assert np.isfinite(np.asarray(adapted.errors)).all()
    # The model it adapts with is the member's: the same Jacobian as the member's own forward model.
    predict, trained = cfg.emitter.forward_model(state.emitter, get_task(cfg))
    own, _ = model.forward_model(state.emitter.members[1], get_task(cfg))
    a = state.repertoire.actions[0]
    np.testing.assert_array_equal(compiled(jax.jacfwd(predict))(a), compiled(jax.jacfwd(own))(a))
    assert bool(trained)
    qd_only = tiny(task="obstacle2d", algorithm=SideBySide((presets.qd(), presets.random())), max_generations=2)
    with pytest.raises(ValueError, match="needs a run whose emitter has a model"):
        adapt(run_mqd(jax.random.PRNGKey(0), qd_only)[0], goals, jax.random.PRNGKey(2), qd_only, "model")


@pytest.mark.parametrize("kwargs, match", [
    (dict(members=(IsoLine(),)), r"SideBySide\.members=.*two or more"),
    (dict(members=(IsoLine(), "qd")), r"SideBySide\.members="),
    (dict(members=(IsoLine(), Uniform()), shares=(0.5, 0.6)), r"SideBySide\.shares=.*summing to 1"),
    (dict(members=(IsoLine(), Uniform(), IsoLine()), shares=Fallback()), r"a share divides the rows between two"),
    (dict(members=(IsoLine(), Uniform()), names=("a", "a")), r"SideBySide\.names=.*distinct"),
])
def test_bad_side_by_side_is_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SideBySide(**kwargs)


def test_a_share_too_small_for_the_population_is_refused(tiny):
    with pytest.raises(ValueError, match=r"gives the members \(0, 16\) of a population of 16"):
        tiny(algorithm=SideBySide((IsoLine(), Uniform()), shares=(0.01, 0.99)))
