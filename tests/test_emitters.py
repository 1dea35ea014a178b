"""Emitters compose without editing the library; the presets are compositions; the core never imports the tasks."""

import dataclasses
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiled import compiled

from mqd_jax import (
    Budgeted,
    Config,
    Emitter,
    IsoLine,
    ModelEmitter,
    Params,
    Proposal,
    Surrogate,
    Threshold,
    Uniform,
    Validity,
    presets,
    run_mqd,
)
from mqd_jax.core.emitter import action_bounds
from mqd_jax.core.registry import make
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.state import METRICS
from mqd_jax.emitters.acquisition import Judged


def test_importing_mqd_jax_and_its_modules_leaves_the_tasks_out():
    modules = ", ".join(f"mqd_jax.experiment.{m}" for m in ("cli", "results", "plots", "sweep", "checkpoint"))
    code = (f"import sys, mqd_jax, {modules}; "
            "print(sorted(m for m in sys.modules if m == 'envs' or m.startswith('envs.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_presets_are_these_compositions():
    model_settings = dict(hidden_size=8, batch_size=4, num_batches=3, warmup_samples=5)
    cfg = Config(algorithm="mqd-paper", k=4, algorithm_options=model_settings, max_generations=2)
    assert Config(algorithm="random").emitter == presets.random() == Uniform()
    assert Config(algorithm="qd").emitter == presets.qd() == IsoLine()
    surrogate = Surrogate(**{k: v for k, v in model_settings.items() if k != "warmup_samples"})
    assert cfg.emitter == presets.mqd_paper(k=4, **model_settings) == ModelEmitter(IsoLine(), Threshold(), surrogate,
                                                                                   k=4, warmup_samples=5)
    budgeted = Config(algorithm="mqd-paper", k=4, algorithm_options={**model_settings, "budgeted": True,
                                                                     "pool_factor": 3}, max_generations=2)
    assert budgeted.emitter == ModelEmitter(IsoLine(), Budgeted(3), surrogate, k=4, warmup_samples=5)
    emitter = ModelEmitter(Uniform(), Budgeted(2))
    assert dataclasses.replace(cfg, algorithm=emitter, algorithm_options={}).emitter is emitter


def test_a_composed_model_emitter_runs_bit_identical_to_the_mqd_paper_preset(tiny):
    preset = tiny(algorithm="mqd-paper", warmup_samples=48, num_batches=10, max_generations=6, t_nov=0.1, t_qua=0.1)
    o = preset.options
    composed = dataclasses.replace(preset, algorithm_options={}, algorithm=ModelEmitter(
        IsoLine(), Threshold(t_nov=0.1, t_qua=0.1), Surrogate(hidden_size=o["hidden_size"],
                                                              batch_size=o["batch_size"], num_batches=o["num_batches"]),
        k=preset.k, warmup_samples=o["warmup_samples"]))
    (s1, m1), (s2, m2) = (run_mqd(jax.random.PRNGKey(1), c) for c in (preset, composed))
    assert set(m1) == set(m2) == set(METRICS) | {"discarded", "model_loss", "prediction_error", "opener_auc"}
    for name in m1:
        np.testing.assert_array_equal(m1[name], m2[name], err_msg=name)
    for a, b in zip(jax.tree.leaves(s1), jax.tree.leaves(s2), strict=True):
        np.testing.assert_array_equal(a, b)
    assert m1["discarded"][-1] > 0  # the model filtered after warm-up (thresholds above the defaults)


def test_qd_and_random_carry_no_model_and_report_only_the_engines_metrics(tiny):
    state, metrics = run_mqd(jax.random.PRNGKey(0), tiny(algorithm="random", max_generations=2))
    assert state.emitter == () and set(metrics) == set(METRICS)


def test_acquisition_rules_respect_the_inner_emitters_rollout_mask_by_hand():
    novelty = jnp.array([0.5, 0.01, 0.9, 0.02, 0.3, 0.0])
    improvement = jnp.array([0.0, 0.5, 0.0, -0.1, 0.0, 0.2])
    wanted = jnp.array([True, True, False, True, True, True])
    params = Params(jnp.float32(0.02), Threshold(t_nov=0.1, t_qua=0.1).default_params())
    judged = Judged(jnp.zeros((6, 2)), jnp.zeros(6), jnp.zeros(6), jnp.zeros(6), jnp.zeros(6), novelty, improvement)
    rep = Repertoire.empty(4, 1, 2, 4)
    key = jax.random.PRNGKey(0)
    rows, rollout, discarded = Threshold().select(key, (), judged, rep, wanted, params, 6)
    # Passing: 0 and 4 by novelty, 1 and 5 by improvement; 2 passes too but the inner emitter did not want it.
    np.testing.assert_array_equal(rows, np.arange(6))
    np.testing.assert_array_equal(rollout, [True, True, False, False, True, True])
    assert int(discarded) == 1  # 3: wanted, turned down
    rows, rollout, discarded = Budgeted(2).select(key, (), judged, rep, wanted, params, 3)
    # Wanted first; of those, novel (> 0.1) by novelty: 0 (0.5), 4 (0.3); then by improvement: 1 (0.5).
    np.testing.assert_array_equal(rows, [0, 4, 1])
    assert bool(rollout.all()) and int(discarded) == 3


@dataclasses.dataclass(frozen=True)
class _WrongShape(Emitter):
    def propose(self, key, state, repertoire, task, params, num):
        return Proposal(jnp.zeros((num + 1, task.action_dim)), jnp.ones(num + 1, bool))


@dataclasses.dataclass(frozen=True)
class _Undeclared(Emitter):
    def propose(self, key, state, repertoire, task, params, num):
        return Uniform().propose(key, state, repertoire, task, params, num)

    def update(self, key, state, proposal, evaluated, repertoire, task, params):
        return state, {"surprise": jnp.float32(1.0)}


@pytest.mark.parametrize(("emitter", "match"), [
    (_WrongShape(), r"propose returned actions \(17, 9\).*expected \(16, 9\) and \(16,\) bool"),
    (_Undeclared(), r"update returned the metrics \['surprise'\], but its metrics\(\) declares \[\]"),
])
def test_an_emitter_that_breaks_the_protocol_is_named_while_tracing(tiny, emitter, match):
    with pytest.raises(ValueError, match=match):
        jax.eval_shape(lambda k: run_mqd(k, tiny(algorithm=emitter)), jax.random.PRNGKey(0))


def test_bad_compositions_are_refused_at_construction():
    with pytest.raises(ValueError, match=r"ModelEmitter.inner=.* expected an Emitter"):
        ModelEmitter("qd")
    with pytest.raises(ValueError, match=r"Surrogate\.hidden_size=0"):
        Surrogate(hidden_size=0)
    with pytest.raises(ValueError, match=r"ModelEmitter\.surrogate=.* expected a surrogate"):
        ModelEmitter(IsoLine(), surrogate=Validity())
    clash = r"metrics \['discarded', 'model_loss', 'opener_auc', 'prediction_error'\] are declared by more than one"
    with pytest.raises(ValueError, match=clash):
        ModelEmitter(ModelEmitter(IsoLine()))
    with pytest.raises(ValueError, match=r"Budgeted\.pool_factor=0"):
        Budgeted(0)
    with pytest.raises(ValueError, match=r"Config\.algorithm='cmaes' is invalid: expected an Emitter or one of"):
        Config(algorithm="cmaes")


def test_isoline_scales_vary_each_part_by_its_scale_from_its_own_key():
    """One skill at the action box's centre, so both parents are it and a child's step from it is the iso noise
    alone: part i of `IsoLine(scales)` is the one-scale child of key fold_in(key, i), its step times scales[i]."""
    task = make("obstacle2d")
    low, high = (np.asarray(b, np.float32) for b in action_bounds(task))
    centre = (low + high) / 2
    rep = Repertoire.empty(8, centre.size, 2, 4)
    rep = rep.replace(actions=rep.actions.at[0].set(centre), valid=jnp.arange(8) < 1, count=jnp.int32(1),
                      novelty=rep.novelty.at[0].set(1.0))
    params, key = Config().params(), jax.random.PRNGKey(7)

    def steps(emitter, key, num):
        proposal = compiled(emitter.propose)(key, (), rep, task, params, num)
        np.testing.assert_array_equal(proposal.parents, 0)
        return np.asarray(proposal.actions) - centre

    # Steps are differences from the centre, so they agree to its last bit's rounding (atol), not exactly.
    unit = [steps(IsoLine(), jax.random.fold_in(key, i), size) for i, size in enumerate((3, 2, 2))]
    mixed = steps(IsoLine(scales=(1.0, 3.0, 0.5)), key, 7)  # 7 = 3 + 2 + 2: the first part one larger
    np.testing.assert_array_equal(mixed[:3], unit[0])
    np.testing.assert_allclose(mixed[3:5], 3.0 * unit[1], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(mixed[5:], 0.5 * unit[2], rtol=1e-5, atol=1e-5)
    assert np.abs(mixed[3:5]).max() > 0  # the steps are not all zero (no clipping at the centre)
    # One scale draws from the key itself; (1.0,) is the paper's QD.
    np.testing.assert_allclose(steps(IsoLine(scales=(2.0,)), key, 4), 2.0 * steps(IsoLine(), key, 4), rtol=1e-5,
                               atol=1e-5)
    assert IsoLine(scales=(1.0,)) == IsoLine()


@pytest.mark.parametrize("scales", [(), (1.0, 0.0), (1.0, -2.0), (float("inf"),), (float("nan"),), [1.0, 2.0],
                                    (True,), ("2",)])
def test_isoline_refuses_bad_scales(scales):
    with pytest.raises(ValueError, match=r"IsoLine\.scales"):
        IsoLine(scales=scales)
