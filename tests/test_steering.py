"""Steering: children aimed by the model's Jacobian, checked on a task whose Jacobian is known, and in a
ModelEmitter's pool."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiled import compiled

import mqd_jax
from mqd_jax import (
    Anchoring,
    Config,
    Diverse,
    Fallback,
    Imagination,
    IsoLine,
    ModelEmitter,
    Steering,
    Surrogate,
    Threshold,
    run_mqd,
)
from mqd_jax.core import repertoire as repertoire_lib
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.emitters.parts import View
from mqd_jax.surrogate import model

T_DIST = 0.02
# The conftest task's behavior: 0.5 + A a.
A = 0.2 * np.array([[1.0, -1.0, 0.0], [0.5, 0.0, 1.0]], np.float32)


@dataclasses.dataclass
class Params:
    t_dist: jax.Array = dataclasses.field(default_factory=lambda: jnp.float32(T_DIST))


def wide(linear_task):
    """The linear task with an action box so wide that no steered child is clipped."""
    return type(linear_task)((-10.0,) * 3, (10.0,) * 3, linear_task.behavior_low, linear_task.behavior_high)


def skills_at(task, actions):
    """A repertoire holding skills of the given actions [n, 3] with their true outcomes."""
    a = jnp.asarray(actions, jnp.float32)
    b, q, valid = task.evaluate(a, None)
    rep = Repertoire.empty(16, 3, 2, repertoire_lib.NUM_NEAR)
    return compiled(repertoire_lib.insert)(rep, a, b, q, valid, jnp.float32(T_DIST), 3, repertoire_lib.NUM_NEAR,
                                           chunk=4)[0]


def linear_jacobian(actions):
    return jnp.broadcast_to(jnp.asarray(A), (actions.shape[0], *A.shape))


# Skills 0.04 and 0.03 apart (behaviors (0.5, 0.5), (0.54, 0.5), (0.5, 0.53)): closer than two steps.
CLOSE = [[0.0, 0.0, 0.0], [0.2, 0.0, -0.1], [0.0, 0.0, 0.15]]


def test_a_steered_child_is_a_min_norm_step_from_the_skill_nearest_to_it(linear_task):
    task = wide(linear_task)
    rep = skills_at(task, CLOSE)
    children, named = compiled(Steering(step_low=1.0, step_high=3.0).steer)(jax.random.PRNGKey(0), rep, linear_jacobian,
                                                                  task, Params(), 400)
    b, _, _ = task.evaluate(children, None)
    skills = np.asarray(rep.behaviors[:3])
    d = np.linalg.norm(np.asarray(b)[:, None] - skills[None], axis=-1)
    parent = d.argmin(1)
    # The step toward a target stays in the parent's Voronoi cell (convex, holding both ends): the nearest skill
    # to the child is its parent, at most 3 t_dist away, and at least t_dist unless the target was nearer (a
    # target within t_dist of a skill: a chance of about 0.4%).
    step = d.min(1)
    assert (step <= 3 * T_DIST + 1e-5).all() and (step < T_DIST - 1e-5).mean() < 0.02
    assert len(set(parent)) == 3
    np.testing.assert_array_equal(named, parent)  # the parents it names are the ones stepped from
    # The action changed by the least-norm change that makes the behavior change: pinv(A) (b' - b_j).
    change = np.asarray(children) - np.asarray(CLOSE, np.float32)[parent]
    expected = (np.linalg.pinv(A) @ (np.asarray(b) - skills[parent]).T).T
    np.testing.assert_allclose(change, expected, atol=1e-5)


def test_a_step_longer_than_the_way_ends_on_the_target(linear_task):
    # Targets are uniform in the behavior box: the children of steps that reach them are, too.
    task = wide(linear_task)
    rep = skills_at(task, CLOSE)
    children, _ = compiled(Steering(step_low=100.0, step_high=100.0).steer)(jax.random.PRNGKey(1), rep, linear_jacobian,
                                                                  task, Params(), 2000)
    b = np.asarray(task.evaluate(children, None)[0])
    assert (b > -1e-5).all() and (b < 1 + 1e-5).all()
    np.testing.assert_allclose(b.mean(0), [0.5, 0.5], atol=0.03)
    np.testing.assert_allclose(b.std(0), [12 ** -0.5] * 2, atol=0.02)


def test_novelty_parents_step_in_every_direction(linear_task):
    task = wide(linear_task)
    rep = skills_at(task, CLOSE[:1])
    children, _ = compiled(Steering(parents="novelty").steer)(jax.random.PRNGKey(3), rep, linear_jacobian, task,
                                                              Params(), 400)
    offset = np.asarray(task.evaluate(children, None)[0]) - np.asarray(rep.behaviors[0])
    step = np.linalg.norm(offset, axis=1)
    assert (step >= T_DIST - 1e-5).all() and (step <= 3 * T_DIST + 1e-5).all()
    assert np.linalg.norm((offset / step[:, None]).mean(0)) < 0.1  # no preferred direction
    assert (offset > 0).any(0).all() and (offset < 0).any(0).all()


def test_a_mutation_step_is_an_iso_mutation_of_the_drawn_skill_without_the_model(linear_task):
    task = wide(linear_task)
    rep = skills_at(task, CLOSE[:1])

    def no_model(actions):
        raise AssertionError("a mutation step asks the model for no Jacobian")

    steering = Steering(step="mutation", iso_sigma=0.03)
    children, parents = compiled(steering.steer)(jax.random.PRNGKey(4), rep, no_model, task, Params(), 4000)
    np.testing.assert_array_equal(parents, 0)  # the one skill
    change = np.asarray(children) - np.asarray(CLOSE[0], np.float32)
    np.testing.assert_allclose(change.mean(0), 0.0, atol=0.02)
    np.testing.assert_allclose(change.std(0), 0.03 * 20.0, rtol=0.05)


def test_a_quality_step_climbs_the_gradient_without_moving_the_linearized_behavior(linear_task):
    task = wide(linear_task)
    rep = skills_at(task, CLOSE)
    gradient = jnp.asarray([0.3, 1.0, -0.4], jnp.float32)
    ascent = lambda actions: jnp.broadcast_to(gradient, actions.shape)  # noqa: E731
    key, num = jax.random.PRNGKey(5), 200
    plain = np.asarray(compiled(Steering().steer)(key, rep, linear_jacobian, task, Params(), num)[0])
    climbing = compiled(Steering(quality=2.0).steer)
    climbed = np.asarray(climbing(key, rep, linear_jacobian, task, Params(), num, ascent)[0])
    extra = climbed - plain  # the same parents and aims: only the null-space step differs
    np.testing.assert_allclose(extra @ A.T, 0.0, atol=1e-5)  # A's null space: the behavior is unchanged
    parents = np.asarray(rep.actions)[np.linalg.norm(
        np.asarray(task.evaluate(jnp.asarray(plain), None)[0])[:, None] - np.asarray(rep.behaviors[:3])[None],
        axis=-1).argmin(1)]
    behavior_step = np.linalg.norm(plain - parents, axis=1)
    np.testing.assert_allclose(np.linalg.norm(extra, axis=1), 2.0 * behavior_step, rtol=1e-4)
    # Along the null-space direction, which for a 1-D null space is +-(its unit vector), the sign g's.
    null = np.linalg.svd(A)[2][-1]
    assert (np.sign(extra @ null) == np.sign(float(np.asarray(gradient) @ null))).all()


def test_steered_children_stay_in_the_action_box(linear_task):
    rep = skills_at(linear_task, [[0.99, -0.99, 0.99]])
    children, _ = compiled(Steering(step_low=50.0, step_high=50.0).steer)(jax.random.PRNGKey(2), rep, linear_jacobian,
                                                                linear_task, Params(), 64)
    assert (np.abs(np.asarray(children)) <= 1.0).all()
    assert (np.abs(np.asarray(children)) == 1.0).any()  # some were clipped


@pytest.mark.parametrize(("kwargs", "match"), [({"share": 1.0}, "share"), ({"share": 0.0}, "share"),
                                               ({"step_low": 2.0, "step_high": 1.0}, "step_low"),
                                               ({"step_high": True}, "step_high"),
                                               ({"parents": "uniform"}, "parents"),
                                               ({"pursuit": 0.5}, "pursuit"), ({"step": "line"}, "step"),
                                               ({"quality": -1.0}, "quality"),
                                               # No step is infinite (refused since the shared checks).
                                               ({"step_high": float("inf")}, "step_high"),
                                               ({"quality": float("inf")}, "quality"),
                                               ({"quality": 1.0, "step": "mutation"}, "quality")])
def test_bad_steering_is_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Steering(**kwargs)


def test_steering_needs_a_ranking_rule_and_is_not_imagined():
    with pytest.raises(ValueError, match="ranking acquisition rule"):
        ModelEmitter(IsoLine(), Threshold(), parts=(Steering(),))
    with pytest.raises(ValueError, match=r"Steering\(.*\) needs a ranking acquisition rule"):
        ModelEmitter(IsoLine(), Imagination(), parts=(Steering(),))


def steered_by(emitter, key, state, pool, rep, task, params, num, warm_up):
    """The pool as the emitter's steering part's pool stage leaves it, and which rows it steered."""
    def pool_stage(key, state, pool, rep, params, warm_up):
        view = View(emitter.model, state.surrogate, rep, task, params, num, warm_up)
        return emitter.part("steering").pool(key, state.parts["steering"], pool, view)

    return compiled(pool_stage)(key, state, pool, rep, params, warm_up)


def test_the_model_s_pool_is_steered_after_warm_up_only(linear_task):
    """The last rows of the pool are steered children whose predicted behavior moved by the step the model's
    Jacobian was asked for (a small step, where the network is nearly linear); the first rows are the inner
    emitter's; during warm-up the pool is the inner emitter's."""
    emitter = ModelEmitter(IsoLine(), Diverse(pool_factor=4), Surrogate(hidden_size=8), warmup_samples=10,
                           parts=(Steering(share=0.5, step_low=0.05, step_high=0.05),))
    state = compiled(emitter.init)(jax.random.PRNGKey(0), linear_task, 64)
    state = state.replace(surrogate=state.surrogate.replace(model=model.init(jax.random.PRNGKey(3), 8, linear_task)))
    predict = lambda actions: emitter.surrogate.predict(state.surrogate, actions, linear_task)  # noqa: E731
    rep = skills_at(linear_task, [[0.1, -0.2, 0.3]])
    params, key = Config().params(), jax.random.PRNGKey(4)
    pool = compiled(emitter.inner.propose)(key, state.inner, rep, linear_task, params, 40)
    for warm_up, steered_rows in ((True, 0), (False, 20)):
        got, steered = steered_by(emitter, jax.random.PRNGKey(5), state, pool, rep, linear_task, params, 10,
                                        jnp.bool_(warm_up))
        np.testing.assert_array_equal(np.asarray(steered), np.arange(40) >= 40 - steered_rows)
        np.testing.assert_array_equal(got.actions[:40 - steered_rows], pool.actions[:40 - steered_rows])
    children = got.actions[20:]
    moved = predict(children)[0] - predict(rep.actions[:1])[0]
    np.testing.assert_allclose(np.linalg.norm(np.asarray(moved), axis=1), 0.05 * float(params.t_dist), rtol=0.05)
    with pytest.raises(ValueError, match="leaving the inner emitter"):
        steered_by(emitter, key, state, pool, rep, linear_task, params, 25, jnp.bool_(False))
    # With a quality step (through the network's own quality gradient) the same children also climb the
    # predicted quality, while their predicted behavior still moves by the asked step.
    climbing = dataclasses.replace(emitter, parts=(dataclasses.replace(emitter.part("steering"), quality=1.0),))
    climbed = steered_by(climbing, jax.random.PRNGKey(5), state, pool, rep, linear_task, params, 10,
                                jnp.bool_(False))[0].actions[20:]
    behaviors, qualities = predict(climbed)
    moved = behaviors - predict(rep.actions[:1])[0]
    np.testing.assert_allclose(np.linalg.norm(np.asarray(moved), axis=1), 0.05 * float(params.t_dist), rtol=0.1)
    assert (np.asarray(qualities) > np.asarray(predict(children)[1])).all()


def test_a_child_whose_jacobian_is_not_finite_keeps_the_inner_candidate(linear_task):
    """Steering differentiates in reverse mode here (d 2 < n 3), where a feature's masked branch (a norm at 0
    under a `where`) gives a NaN Jacobian that forward mode would not: the children of the parent at such an
    action are not steered (their rows keep the inner emitter's candidates), the other parent's are."""

    class Masked(type(linear_task)):
        def features(self, actions):
            norm = jnp.linalg.norm(actions[:, 1:], axis=1, keepdims=True)
            return jnp.where(actions[:, :1] > 0, norm, 0.0)

    task = Masked(linear_task.action_low, linear_task.action_high, linear_task.behavior_low,
                  linear_task.behavior_high)
    emitter = ModelEmitter(IsoLine(), Diverse(pool_factor=4), Surrogate(hidden_size=8, features=True),
                           parts=(Steering(share=0.5),))
    state = compiled(emitter.init)(jax.random.PRNGKey(0), task, 64)
    rep = skills_at(task, [[-0.5, 0.0, 0.0], [0.5, 0.3, 0.1]])  # the first: a masked norm at 0
    params = mqd_jax.Params(jnp.float32(T_DIST), emitter.default_params())
    pool = compiled(emitter.inner.propose)(jax.random.PRNGKey(1), state.inner, rep, task,
                                           params.part(params.emitter.inner), 400)
    got, steered = steered_by(emitter, jax.random.PRNGKey(2), state, pool, rep, task, params, 100, jnp.bool_(False))
    # The steering parents do not depend on the Jacobian: the same key with a finite one draws them.
    parents = np.asarray(compiled(emitter.part("steering").steer)(jax.random.fold_in(jax.random.PRNGKey(2), 2), rep,
                                                           linear_jacobian, task, params, 200)[1])
    assert 0 < (parents == 0).sum() < 200  # both parents were drawn
    assert np.isfinite(np.asarray(got.actions)).all()
    np.testing.assert_array_equal(np.asarray(steered), np.r_[np.zeros(200, bool), parents == 1])
    np.testing.assert_array_equal(got.actions[~np.asarray(steered)], pool.actions[~np.asarray(steered)])
    forward = jax.vmap(jax.jacfwd(lambda a: emitter.surrogate.predict(state.surrogate, a, task)[0]))
    assert np.isfinite(np.asarray(forward(rep.actions[:2]))).all()


def test_a_proposal_names_each_candidate_s_parent_steered_or_not(linear_task):
    """With no variation (sigmas 0) every child is its parent's action: IsoLine's and a mutation step's alike, so
    the parents a ModelEmitter's proposal names (IsoLine's first parents, the steered rows' steering parents,
    kept with the rows the rule chose) hold exactly the proposed actions."""
    emitter = ModelEmitter(IsoLine(iso_sigma=0.0, line_sigma=0.0), Diverse(pool_factor=4),
                           Surrogate(hidden_size=8), parts=(Steering(share=0.5, step="mutation", iso_sigma=0.0),
                                                            Anchoring("always")))
    state = compiled(emitter.init)(jax.random.PRNGKey(0), linear_task, 64)
    rep = skills_at(linear_task, [[0.1 * i, -0.05 * i, 0.02 * i * i] for i in range(8)])
    params = mqd_jax.Params(jnp.float32(T_DIST), emitter.default_params())
    inner = params.part(params.emitter.inner)
    pool = compiled(emitter.inner.propose)(jax.random.PRNGKey(1), state.inner, rep, linear_task, inner, 48)
    steered_pool, steered = steered_by(emitter, jax.random.PRNGKey(2), state, pool, rep, linear_task, params, 12,
                                             jnp.bool_(False))
    assert steered.sum() == 24 and (np.asarray(steered_pool.parents) >= 0).all()
    np.testing.assert_array_equal(steered_pool.actions, np.asarray(rep.actions)[np.asarray(steered_pool.parents)])
    proposal = compiled(emitter.propose)(jax.random.PRNGKey(1), state, rep, linear_task, params, 12)
    parents = np.asarray(proposal.parents)
    assert (parents >= 0).all() and len(set(parents)) > 1
    np.testing.assert_array_equal(proposal.actions, np.asarray(rep.actions)[parents])
    # Before the first skill there is no parent: IsoLine's uniform candidates name -1.
    first = compiled(IsoLine().propose)(jax.random.PRNGKey(2), (), Repertoire.empty(16, 3, 2, 4), linear_task, inner, 5)
    np.testing.assert_array_equal(first.parents, -1)


def test_a_steered_run_reports_its_steered_rollouts(tiny):
    steered = ModelEmitter(IsoLine(), Diverse(), Surrogate(hidden_size=8, num_batches=2), warmup_samples=16,
                           parts=(Steering(),))
    cfg = tiny(algorithm=steered, max_generations=4)
    _, metrics = run_mqd(jax.random.PRNGKey(0), cfg)
    count = np.asarray(metrics["steered"])
    assert count[0] == 0  # warm-up
    assert (count[1:] > 0).all() and (count <= cfg.population_size).all()


def test_a_steering_pursuit_moves_its_share_by_the_pursuit_rule(tiny):
    pursuit = Fallback(floor=0.1, rate=0.2)
    steered = ModelEmitter(IsoLine(), Diverse(), Surrogate(hidden_size=8, num_batches=2), warmup_samples=16,
                           parts=(Steering(share=0.5, pursuit=pursuit),))
    cfg = tiny(algorithm=steered, max_generations=6)
    _, metrics = run_mqd(jax.random.PRNGKey(1), cfg)
    share, count = np.asarray(metrics["steering_share"]), np.asarray(metrics["steered"])
    pool = Diverse().pool_size(cfg.population_size)
    assert share[0] == share[1] == 0.5  # nothing compared during warm-up, nor before a generation with both sides
    assert (count <= np.round(share * round(0.5 * pool))).all() and count[1] > 0
    # Each later generation moves the share a fifth of the way toward 0.9 or 0.1 (or keeps it: no comparison yet).
    target = (share[2:] - 0.8 * share[1:-1]) / 0.2
    moved = ~np.isclose(share[2:], share[1:-1])
    assert np.isclose(target[moved][:, None], [0.1, 0.9], atol=1e-4).any(1).all()
    assert moved.any()
