import re

import jax
import numpy as np
import pytest

from mqd_jax import Config, init, run_mqd
from mqd_jax.core import registry
from mqd_jax.core.run import generation


@pytest.mark.parametrize("task", ["obstacle2d", "object2d"])
def test_coverage_grows_and_metrics_are_consistent(task, tiny):
    cfg = tiny(task=task)
    state, m = run_mqd(jax.random.PRNGKey(0), cfg)
    cov = np.asarray(m["coverage"])
    assert cov[-1] > cov[0] > 0
    assert m["coverage"].shape == (cfg.max_generations,)
    pop = cfg.population_size
    np.testing.assert_array_equal(m["evaluations"], pop)
    np.testing.assert_array_equal(m["num_evaluations"], pop * np.arange(1, cfg.max_generations + 1))
    np.testing.assert_array_equal(np.cumsum(m["added"]), m["repertoire_size"])
    outcomes = m["added"] + m["replaced"] + m["rejected"] + m["dropped_full"] + m["invalid"]
    np.testing.assert_array_equal(outcomes, pop)
    rep = state.repertoire
    n = int(rep.count)
    assert int(rep.valid.sum()) == n and bool(rep.valid[:n].all())
    # Every evaluated skill that was not added went to the archive, or replaced one that did.
    assert int(state.archive.total) == int(m["num_evaluations"][-1] - m["invalid"].sum() - m["added"].sum())
    q = np.asarray(rep.qualities[:n])
    assert float(m["mean_quality"][-1]) == pytest.approx(q.mean(), rel=1e-5)
    # The standard metrics (pyribs' and QDax's definitions): QD-score = sum of (quality - the task's lowest quality).
    q_low = cfg_task(cfg).quality_range[0]
    assert float(m["max_quality"][-1]) == pytest.approx(q.max(), rel=1e-6)
    assert float(m["qd_score"][-1]) == pytest.approx((q - q_low).sum(), rel=1e-5)
    low, high = np.asarray(cfg_task(cfg).action_low), np.asarray(cfg_task(cfg).action_high)
    a = np.asarray(rep.actions[:n])
    assert np.all((a >= low) & (a <= high))


def cfg_task(cfg):

    return registry.make(cfg.task)


def test_same_key_same_result_and_vmap_over_keys(tiny, assert_same):
    cfg = tiny()
    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    s1, m1 = run_mqd(keys[1], cfg)
    s2, m2 = run_mqd(keys[1], cfg)
    for a, b in zip(jax.tree.leaves((s1, m1)), jax.tree.leaves((s2, m2)), strict=True):
        np.testing.assert_array_equal(a, b)
    sv, mv = jax.vmap(lambda k: run_mqd(k, cfg))(keys)
    for a, b in zip(jax.tree.leaves((s1, m1)), jax.tree.leaves((sv, mv)), strict=True):
        assert_same(a, b[1])


def test_full_repertoire_counts_dropped_niches_and_keeps_replacing(tiny):
    cfg = tiny(capacity=20, population_size=16, max_generations=10)
    state, m = run_mqd(jax.random.PRNGKey(0), cfg)
    assert int(state.repertoire.count) == 20
    assert int(m["dropped_full"].sum()) > 0
    full = np.asarray(m["repertoire_size"]) == 20
    assert np.asarray(m["replaced"])[full].sum() > 0


def test_default_params_give_the_same_run_as_the_same_params_passed_in():
    # Without care XLA folds the config's constants into the arithmetic and rounds differently.
    cfg = Config(max_generations=10, capacity=1024)
    key = jax.random.PRNGKey(0)
    for a, b in zip(jax.tree.leaves(run_mqd(key, cfg)), jax.tree.leaves(run_mqd(key, cfg, cfg.params())), strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_generation_reads_as_named_stages(tiny):
    cfg = tiny(algorithm="mqd", warmup_samples=16, num_batches=2)
    state = init(jax.random.PRNGKey(0), cfg)
    text = jax.jit(generation, static_argnums=1).lower(state, cfg, cfg.params()).as_text(debug_info=True)
    for name in ("emit/inner", "emit/steering", "emit/predict", "emit/acquire", "evaluate", "insert", "archive",
                 "coverage", "update/train", "metrics"):
        assert re.search(rf'["/]{name}/', text), name  # an operation's location: .../emit/predict/...
