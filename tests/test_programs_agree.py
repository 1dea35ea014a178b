"""Two compiled programs of one computation give the same run, bit for bit: ask/tell around a numpy evaluator and
the fused generation; a checkpointed run resumed and the uninterrupted one; the paper's M-QD with a filter that
passes everything and QD; traced params and a static config, vmapped; a validity classifier with nothing to judge
and none.

With the elemental emitters the rest of the suite compiles with, two programs may round a float32 differently
(conftest.py), so this module runs in a process of its own with XLA's default emitters, as users run: one start-up
for all of them, and the programs they share (the tiny M-QD run) compiled once.
"""

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mqd_jax import (
    Anchoring,
    Diverse,
    Fallback,
    IsoLine,
    ModelEmitter,
    Steering,
    Surrogate,
    Task,
    Validity,
    ask,
    init,
    run_mqd,
    tell,
)
from mqd_jax.core import registry
from mqd_jax.experiment import checkpoint
from mqd_jax.experiment import progress as progress_lib

pytestmark = pytest.mark.fusion_emitters

# The tiny M-QD run several tests compare with: one program for them all.
MQD = dict(task="obstacle2d", algorithm="mqd", warmup_samples=64, num_batches=20)


def assert_trees_equal(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)


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


@pytest.mark.parametrize("algorithm", ["qd", "mqd"])
def test_ask_tell_with_a_numpy_evaluator_equals_the_fused_run(algorithm, tiny):
    cfg = tiny(**{**MQD, "algorithm": algorithm})
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


class Crash(Exception):
    pass


class CrashAfter(progress_lib.Progress):
    """Crashes the run after its `chunks`-th chunk (its checkpoint saved)."""

    def __init__(self, chunks):
        self.chunks, self.seen = chunks, []

    def chunk(self, done, metrics):
        self.seen.append(done)
        if len(self.seen) == self.chunks:
            raise Crash


# A quality step's comparison of predicted qualities tells a float32 rounded differently apart.
def test_a_resumed_run_equals_the_uninterrupted_one(tmp_path, tiny):
    cfg, key = tiny(**MQD), jax.random.PRNGKey(3)
    path = str(tmp_path / "run.ckpt")
    with pytest.raises(Crash):
        checkpoint.run_with_checkpoints(key, cfg, path, every=5, progress=CrashAfter(1))
    state, metrics = checkpoint.load(path, cfg, key)
    assert int(state.generation) == 5 and len(metrics["coverage"]) == 5
    state, metrics = checkpoint.run_with_checkpoints(key, cfg, path, every=5)
    want_state, want_metrics = run_mqd(key, cfg)
    assert_trees_equal(state, want_state)  # repertoire, archive, coverage, model, Adam state, key, counts
    assert metrics.keys() == want_metrics.keys()
    for k in metrics:
        np.testing.assert_array_equal(metrics[k], want_metrics[k], err_msg=k)
    assert os.listdir(tmp_path) == ["run.ckpt"]  # no temporary file left behind


def test_mqd_with_an_always_passing_filter_equals_qd(tiny):
    qd = tiny(task="obstacle2d", algorithm="qd")
    options = dict(t_nov=0.0, t_qua=-1e9, warmup_samples=64, num_batches=20)
    mqd = dataclasses.replace(qd, algorithm="mqd-paper", algorithm_options=options)
    key = jax.random.PRNGKey(4)
    (s_qd, m_qd), (s_mqd, m_mqd) = run_mqd(key, qd), run_mqd(key, mqd)
    assert np.all(np.isfinite(m_mqd["model_loss"][4:])) and int(s_mqd.emitter.surrogate.model.steps) == 20 * 9
    for field in ("repertoire", "archive", "coverage", "key", "generation", "num_evaluations"):
        assert_trees_equal(getattr(s_qd, field), getattr(s_mqd, field))
    for name in m_qd:
        if name not in ("model_loss", "prediction_error"):
            np.testing.assert_array_equal(m_qd[name], m_mqd[name], err_msg=name)


def test_traced_params_match_static_config_and_vmap(tiny, assert_same):
    cfg = tiny()
    other = dataclasses.replace(cfg, algorithm_options={"iso_sigma": 0.1}, t_dist=0.015)
    _, want = run_mqd(jax.random.PRNGKey(0), other)
    params = jax.tree.map(lambda a, b: jnp.stack([a, b]), cfg.params(), other.params())
    _, got = jax.vmap(lambda p: run_mqd(jax.random.PRNGKey(0), cfg, p))(params)
    for key in want:
        assert_same(got[key][1], want[key])


@dataclasses.dataclass(frozen=True, eq=False)
class Usable(Task):
    """Behavior and quality are affine maps of a 3D action; every rollout is usable."""

    def evaluate(self, actions, key):
        b = 0.5 + 0.2 * jnp.stack([actions[:, 0] - actions[:, 1], actions[:, 2] + 0.5 * actions[:, 0]], axis=1)
        return b, 0.5 + 0.3 * actions[:, 1], jnp.full(actions.shape[0], True)


def test_without_unusable_rollouts_a_run_is_the_same_as_without_the_validity_classifier(tiny):
    def composed(validity):
        return ModelEmitter(IsoLine(), Diverse(3), Surrogate(num_batches=5, validity=validity), warmup_samples=32,
                            parts=(Steering(share=0.3), Anchoring("auto"), Fallback()))

    cfg = tiny(task=Usable((-1.0,) * 3, (1.0,) * 3, (0.0, 0.0), (1.0, 1.0)), algorithm=composed(None))
    state, m = run_mqd(jax.random.PRNGKey(0), cfg)
    judged_state, judged_m = run_mqd(jax.random.PRNGKey(0), dataclasses.replace(cfg, algorithm=composed(Validity())))
    assert_trees_equal(state.repertoire, judged_state.repertoire)
    for name in m:
        np.testing.assert_array_equal(m[name], judged_m[name], err_msg=name)
    assert np.all(np.isnan(judged_m["validity_auc"]))  # no unusable rollout to rank against
