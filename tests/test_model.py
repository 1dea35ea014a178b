import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from envs.obstacle2d import Obstacle2D
from mqd_jax import Config, init, run_mqd
from mqd_jax.core import registry
from mqd_jax.core.archive import Archive
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.run import generation
from mqd_jax.emitters import acquisition
from mqd_jax.surrogate import model

POISON = 1e6


@dataclasses.dataclass(frozen=True, eq=False)
class Poisoned(Obstacle2D):
    """Obstacle2D whose rows outside the evaluation mask come back as an unbeatable skill."""

    def evaluate_masked(self, actions, key, mask):
        b, q, v = self.evaluate(actions, key)
        return jnp.where(mask[:, None], b, 0.5), jnp.where(mask, q, POISON), v


POISONED = Poisoned(*dataclasses.astuple(registry.make("obstacle2d"))[:4])


def repertoire_of(behaviors, qualities, capacity=8):
    b = np.asarray(behaviors, np.float32)
    rep = Repertoire.empty(capacity, 1, b.shape[1], 4)
    n = len(b)
    return rep.replace(behaviors=rep.behaviors.at[:n].set(b), qualities=rep.qualities.at[:n].set(qualities),
                       valid=jnp.arange(capacity) < n, count=jnp.int32(n))


def test_filter_scores_and_decision_by_hand():
    rep = repertoire_of([[0.0, 0.0], [0.3, 0.4], [1.0, 0.0]], [0.5, 0.2, 0.9])
    pred_b = jnp.array([[0.0, 0.0], [0.6, 0.8]])
    pred_q = jnp.array([0.6, 0.1])
    nov, qua = acquisition.predicted_scores(pred_b, pred_q, rep, k=2)
    # Candidate 0: nearest are slot 0 (d 0) and slot 1 (d 0.5). Candidate 1: slot 1 (d 0.5), slot 2 (d sqrt(0.8)).
    np.testing.assert_allclose(nov, [0.25, (0.5 + np.sqrt(0.8)) / 2], rtol=1e-6)
    np.testing.assert_allclose(qua, [((0.6 - 0.5) + (0.6 - 0.2)) / 2, ((0.1 - 0.2) + (0.1 - 0.9)) / 2], rtol=1e-6)
    np.testing.assert_array_equal(acquisition.passes(nov, qua, 0.3, 0.0), [True, True])  # 0 by quality, 1 by novelty
    np.testing.assert_array_equal(acquisition.passes(nov, qua, 0.3, 0.3), [False, True])
    np.testing.assert_array_equal(acquisition.passes(nov, qua, 0.7, 0.3), [False, False])
    # Fewer than K skills: the mean runs over those there are; none: everything passes.
    nov1, qua1 = acquisition.predicted_scores(pred_b, pred_q, repertoire_of([[0.3, 0.4]], [0.2]), k=5)
    np.testing.assert_allclose(nov1, [0.5, 0.5], rtol=1e-6)
    np.testing.assert_allclose(qua1, [0.4, -0.1], rtol=1e-6)
    nov0, qua0 = acquisition.predicted_scores(pred_b, pred_q, Repertoire.empty(8, 1, 2, 4), k=5)
    assert np.all(np.isinf(nov0)) and np.all(acquisition.passes(nov0, qua0, 1e9, 1e9))
    assert not acquisition.passes(jnp.array([jnp.nan]), jnp.array([jnp.nan]), 0.0, -1.0)[0]


def test_budgeted_order_by_hand():
    nov = jnp.array([0.05, 0.01, 0.09, 0.02, jnp.nan, 0.05, 0.03])
    qua = jnp.array([0.0, 0.2, -0.1, 0.3, jnp.nan, 0.1, -0.2])
    # Novel (> 0.04): 2, then 0 and 5 tied on novelty -> higher qua first (5, 0).
    # The rest by qua: 3 (0.3), 1 (0.2), 6 (-0.2); the NaN prediction (4) last.
    np.testing.assert_array_equal(acquisition.ranking(nov, qua, 0.04, jnp.ones(7, bool)), [2, 5, 0, 3, 1, 6, 4])


def test_predict_maps_tanh_outputs_to_real_units(linear_task):
    ms = model.init(jax.random.PRNGKey(0), 4, linear_task)
    want = np.array([-0.5, 0.25, 0.8], np.float32)  # normalized behavior x, y and quality
    p = ms.params["params"]  # one member: a leading axis of 1
    params = {"params": {"Dense_0": p["Dense_0"], "Dense_1": {"kernel": jnp.zeros_like(p["Dense_1"]["kernel"]),
                                                              "bias": jnp.arctanh(jnp.asarray(want))[None]}}}
    b, q = model.predict(ms.replace(params=params), jnp.zeros((3, 3)), linear_task)
    # Behavior box [0, 1]^2 and the default quality range (0, 1): x = (y + 1) / 2.
    np.testing.assert_allclose(b, np.broadcast_to([0.25, 0.625], (3, 2)), rtol=1e-5)
    np.testing.assert_allclose(q, [0.9] * 3, rtol=1e-5)


def test_model_learns_a_linear_map(linear_task):
    actions = jax.random.uniform(jax.random.PRNGKey(1), (512, 3), minval=-1.0, maxval=1.0)
    b, q, _ = linear_task.evaluate(actions, None)
    rep = Repertoire.empty(512, 3, 2, 4).replace(actions=actions, behaviors=b, qualities=q,
                                                 valid=jnp.ones(512, bool), count=jnp.int32(512))
    ms = model.init(jax.random.PRNGKey(0), 32, linear_task)
    test = jax.random.uniform(jax.random.PRNGKey(2), (256, 3), minval=-1.0, maxval=1.0)
    tb, tq, _ = linear_task.evaluate(test, None)

    def error(m):
        pb, pq = model.predict(m, test, linear_task)
        return float(jnp.mean((pb - tb) ** 2)), float(jnp.mean((pq - tq) ** 2))

    before = error(ms)
    trained, loss = model.train(ms, jax.random.PRNGKey(3), rep, linear_task, jnp.float32(1e-2), 16, 300)
    after = error(trained)
    assert int(trained.steps) == 300
    assert after[0] < 1e-3 and after[1] < 1e-3, after  # RMS error < 0.03 on a range of ~0.6
    assert after[0] < before[0] / 10 and after[1] < before[1] / 10
    assert np.isfinite(float(loss))


def run(cfg):
    return run_mqd(jax.random.PRNGKey(4), cfg)


def check_masked_rows_left_no_trace(cfg, state, m):
    options = cfg.options
    pop, pool = cfg.population_size, cfg.population_size * (options["pool_factor"] if options["budgeted"] else 1)
    evaluations, discarded = np.asarray(m["evaluations"]), np.asarray(m["discarded"])
    outcomes = m["added"] + m["replaced"] + m["rejected"] + m["dropped_full"] + m["invalid"]
    np.testing.assert_array_equal(outcomes, evaluations)
    np.testing.assert_array_equal(np.cumsum(evaluations), m["num_evaluations"])
    np.testing.assert_array_equal(evaluations + discarded, np.where(discarded > 0, pool, pop))
    assert float(state.repertoire.qualities.max()) < POISON and float(state.archive.qualities.max()) < POISON
    assert int(state.archive.total) == int(evaluations.sum() - m["added"].sum())
    return evaluations, discarded


def test_discarded_candidates_are_never_evaluated_counted_or_inserted(tiny):
    cfg = tiny(task=POISONED, algorithm="mqd-paper", warmup_samples=64, num_batches=50, t_nov=0.05, t_qua=0.05)
    state, m = run(cfg)
    evaluations, discarded = check_masked_rows_left_no_trace(cfg, state, m)
    assert discarded.sum() > 0 and evaluations[4:].min() < cfg.population_size


def test_budgeted_mode_evaluates_exactly_the_population(tiny):
    cfg = tiny(task=POISONED, algorithm="mqd-paper", warmup_samples=64, num_batches=50, budgeted=True,
               pool_factor=3)
    state, m = run(cfg)
    evaluations, discarded = check_masked_rows_left_no_trace(cfg, state, m)
    np.testing.assert_array_equal(evaluations, cfg.population_size)
    np.testing.assert_array_equal(discarded, [0] * 4 + [2 * cfg.population_size] * (cfg.max_generations - 4))


def test_warm_up_runs_as_qd_and_does_not_train(tiny):
    # A filter that turns down everything once the model is in use.
    cfg = tiny(task="obstacle2d", algorithm="mqd-paper", warmup_samples=70, num_batches=10, t_nov=1e3, t_qua=1e3)
    state, m = run(cfg)
    before = np.concatenate([[0], np.asarray(m["num_evaluations"])[:-1]])
    warm = before < cfg.options["warmup_samples"]
    assert warm.sum() == 5  # 5 x 16 = 80 >= 70 evaluations
    np.testing.assert_array_equal(np.asarray(m["discarded"])[warm], 0)
    np.testing.assert_array_equal(np.asarray(m["evaluations"])[warm], cfg.population_size)
    np.testing.assert_array_equal(np.asarray(m["discarded"])[~warm], cfg.population_size)
    # Training starts at the end of the generation that completes warm-up, and then every generation.
    trained = np.isfinite(np.asarray(m["model_loss"]))
    np.testing.assert_array_equal(trained, np.asarray(m["num_evaluations"]) >= cfg.options["warmup_samples"])
    assert int(state.emitter.surrogate.model.steps) == cfg.options["num_batches"] * trained.sum()
    assert np.all(np.isfinite(np.asarray(m["prediction_error"])[warm]))
    assert np.all(np.isnan(np.asarray(m["prediction_error"])[~warm]))  # nothing evaluated


@pytest.mark.parametrize("kw, match", [
    (dict(algorithm="qd", algorithm_options={"budgeted": True}), "'qd' takes no option 'budgeted'"),
    (dict(algorithm="mqd-paper", algorithm_options={"budgeted": 1}), "budgeted=1 is invalid"),
    (dict(algorithm="mqd", algorithm_options={"warmup_samples": 1200}, max_generations=12, population_size=100),
     "ModelEmitter.warmup_samples=1200 is invalid for this run"),
    (dict(algorithm="mqd-paper", algorithm_options={"pool_factor": 0, "budgeted": True}), "Budgeted.pool_factor=0"),
])
def test_model_config_is_validated(kw, match):
    with pytest.raises(ValueError, match=match):
        Config(**kw)


def test_a_training_step_is_one_optax_adam_step_at_the_traced_learning_rate(linear_task):
    ms = model.init(jax.random.PRNGKey(0), 8, linear_task)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (16, 3), minval=-1.0, maxval=1.0)
    b, q, _ = linear_task.evaluate(actions, None)
    rep = Repertoire.empty(16, 3, 2, 4).replace(actions=actions, behaviors=b, qualities=q, valid=jnp.ones(16, bool),
                                                count=jnp.int32(16))
    key, rate = jax.random.PRNGKey(2), 0.05
    trained, loss = model.train(ms, key, rep, linear_task, jnp.float32(rate), 16, 1)
    # The same mini-batch, by hand, through optax.adam.
    rows = jax.random.randint(key, (1, 1, 16), 0, rep.count)[0, 0]
    x = model.normalize_actions(actions[rows], linear_task)
    y = model.normalize_targets(b[rows], q[rows], linear_task)
    net = model.network(8, linear_task)
    member = lambda p: ((net.apply(jax.tree.map(lambda v: v[0], p), x) - y) ** 2).mean()  # noqa: E731
    want_loss, grads = jax.value_and_grad(member)(ms.params)
    adam = optax.adam(rate)
    updates, _ = adam.update(grads, adam.init(ms.params), ms.params)
    want = optax.apply_updates(ms.params, updates)
    for got, expected in zip(jax.tree.leaves(trained.params), jax.tree.leaves(want), strict=True):
        np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7)
    assert float(loss) == pytest.approx(float(want_loss), rel=1e-6)
    # Adam's first step moves every parameter with a gradient by the learning rate.
    step = max(float(jnp.abs(a - c).max()) for a, c in zip(jax.tree.leaves(trained.params),
                                                             jax.tree.leaves(ms.params), strict=True))
    assert step == pytest.approx(rate, rel=1e-3)


@pytest.mark.parametrize(("algorithm", "options", "traced"), [("mqd", {}, 2), ("mqd", {"steering_share": 0.0}, 1),
                                                              ("mqd", {"features": False}, 0), ("qd", {}, 0)])
def test_a_generation_computes_the_tasks_features_of_its_pool_only(algorithm, options, traced, monkeypatch):
    """The repertoire keeps each skill's features (computed once, from the pool that proposed it), so anchors,
    training rows and the gate read them: a generation's program computes the features of its pool, and the
    steering Jacobian differentiates them; nothing else does (QD, or a model without features: none)."""
    calls = []
    features = Obstacle2D.features
    monkeypatch.setattr(Obstacle2D, "features", lambda self, a: calls.append(a.shape) or features(self, a))
    if algorithm == "mqd":
        options = {**options, "warmup_samples": 8}
    cfg = Config(task="obstacle2d", algorithm=algorithm, algorithm_options=options, population_size=8, capacity=64,
                 archive_capacity=16, max_generations=2)
    state = init(jax.random.PRNGKey(0), cfg)
    calls.clear()
    jax.make_jaxpr(lambda s: generation(s, cfg, cfg.params()))(state)
    assert len(calls) == traced, calls


def test_by_novelty_draws_valid_skills_in_proportion_to_novelty_to_the_power():
    rep = Repertoire.empty(8, 1, 2, 4).replace(novelty=jnp.array([0.0, 1.0, 2.0, 3.0, 9.0, 9.0, 9.0, 9.0]),
                                               valid=jnp.arange(8) < 4, count=jnp.int32(4))  # slots 4-7 hold no skill
    keys = jax.random.split(jax.random.PRNGKey(0), 500)

    def shares(r, power):
        drawn = np.asarray(jax.vmap(lambda k: model.by_novelty(k, r, power))(keys)).ravel()
        return np.bincount(drawn, minlength=8) / drawn.size

    np.testing.assert_allclose(shares(rep, 2.0), [0, 1 / 14, 4 / 14, 9 / 14, 0, 0, 0, 0], atol=0.02)
    np.testing.assert_allclose(shares(rep, 1.0), [0, 1 / 6, 2 / 6, 3 / 6, 0, 0, 0, 0], atol=0.02)
    # Where every weight underflows (no skill has a neighbour), uniformly over the skills.
    lonely = rep.replace(novelty=jnp.zeros(8))
    np.testing.assert_allclose(shares(lonely, 20.0), [0.25] * 4 + [0] * 4, atol=0.03)


def test_novelty_sampling_weighs_the_fit_by_novelty_to_the_power(linear_task):
    """Two skills at the same action with other behaviors: the model learns their mean, weighted by novelty ** p."""
    capacity, action = 256, jnp.zeros((1, 3))
    b = jnp.zeros((capacity, 2)).at[0].set(0.6).at[1].set(0.2)
    rep = Repertoire.empty(capacity, 3, 2, 4).replace(
        behaviors=b, qualities=jnp.full(capacity, 0.5), novelty=jnp.zeros(capacity).at[0].set(1.0).at[1].set(0.5),
        valid=jnp.arange(capacity) < 2, count=jnp.int32(2))
    ms = model.init(jax.random.PRNGKey(0), 8, linear_task)

    def fitted(power):
        trained, _ = model.train(ms, jax.random.PRNGKey(1), rep, linear_task, jnp.float32(1e-2), 16, 400,
                                 novelty_power=power)
        return np.asarray(model.predict(trained, action, linear_task)[0])[0]

    np.testing.assert_allclose(fitted(0.0), 0.4, atol=0.03)  # uniform: (0.6 + 0.2) / 2
    np.testing.assert_allclose(fitted(2.0), (0.6 + 0.25 * 0.2) / 1.25, atol=0.03)  # weights 1 and 0.5 ** 2
    with pytest.raises(ValueError, match=r"novelty_power=1\.0 draws by the skills' novelty"):
        model.train(ms, jax.random.PRNGKey(1), Archive.empty(8, 3, 2), linear_task, jnp.float32(1e-2), 16, 1,
                    novelty_power=1.0)
