"""A model emitter's chain of parts: each part's stages run in order, its info keeps the chosen rows, warm-up is
gated once, and a chain that cannot work is refused naming the part."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mqd_jax import Anchoring, Diverse, Fallback, IsoLine, ModelEmitter, Part, Steering, Surrogate, Threshold, run_mqd


@dataclasses.dataclass(frozen=True)
class Recorder(Part):
    """Records each pool row's first action coordinate at its pool stage and each prediction at its predict stage;
    counts the generations it learned from; reports whether the kept rows' records are the proposal's rows."""

    name = "recorder"

    def init(self, key, task):
        return jnp.int32(0)

    def metrics(self):
        return {"learned": jnp.int32, "kept_rows": jnp.bool_, "kept_predictions": jnp.bool_}

    def pool(self, key, state, pool, view):
        return pool, pool.actions[:, 0]

    def predicted(self, state, y, candidates, view):
        return y, y.mean(axis=0)[:, :-1]

    def update(self, state, info, proposal, evaluated):
        return state + 1

    def report(self, state, info, proposal, evaluated):
        return {"learned": state, "kept_rows": (info[0] == proposal.actions[:, 0]).all(),
                "kept_predictions": (info[1] == proposal.info.predicted_behaviors).all()}


@dataclasses.dataclass(frozen=True)
class EagerRecorder(Recorder):
    name = "eager"
    learns_in_warm_up = True

    def metrics(self):
        return {f"eager_{k}": v for k, v in super().metrics().items()}

    def report(self, state, info, proposal, evaluated):
        return {f"eager_{k}": v for k, v in super().report(state, info, proposal, evaluated).items()}


def test_a_part_sees_its_rows_kept_and_learns_after_warm_up_only(tiny):
    emitter = ModelEmitter(IsoLine(), Diverse(4), Surrogate(num_batches=2), warmup_samples=32,
                           parts=(Steering(share=0.25), Recorder(), EagerRecorder(), Fallback()))
    _, m = run_mqd(jax.random.PRNGKey(0), tiny(algorithm=emitter, max_generations=5))
    assert np.asarray(m["kept_rows"]).all() and np.asarray(m["kept_predictions"]).all()
    assert np.asarray(m["eager_kept_rows"]).all()
    # 16 rollouts a generation: warm-up is the first two generations; a part reports the state it chose with.
    np.testing.assert_array_equal(m["learned"], [0, 0, 0, 1, 2])
    np.testing.assert_array_equal(m["eager_learned"], [0, 1, 2, 3, 4])
    assert m["steered"][0] == 0 and m["steered"][-1] > 0  # the steering part ran before the recorder's pool stage


def test_predict_stages_run_in_order(linear_task):
    """Two parts that change the predictions: the chain applies them in its order."""

    @dataclasses.dataclass(frozen=True)
    class Add(Part):
        name = "add"

        def predicted(self, state, y, candidates, view):
            return y + 1.0, ()

    @dataclasses.dataclass(frozen=True)
    class Double(Part):
        name = "double"

        def predicted(self, state, y, candidates, view):
            return 2.0 * y, ()

    actions = jax.random.uniform(jax.random.PRNGKey(1), (5, 3), minval=-1.0, maxval=1.0)
    plain = ModelEmitter(IsoLine(), Diverse(), Surrogate(hidden_size=4))
    state = plain.init(jax.random.PRNGKey(0), linear_task, 16)
    view = plain.view(state, None, linear_task, None, 5)
    x = plain.model.inputs(actions, linear_task)
    y, _ = plain.predicted(state, actions, None, x, view)
    for chain, want in (((Add(), Double()), 2.0 * (y + 1.0)), ((Double(), Add()), 2.0 * y + 1.0)):
        emitter = dataclasses.replace(plain, parts=chain)
        got, _ = emitter.predicted(emitter.init(jax.random.PRNGKey(0), linear_task, 16), actions, None, x, view)
        np.testing.assert_allclose(got, want, rtol=1e-6)


@pytest.mark.parametrize("kwargs, match", [
    (dict(parts=[Fallback()]), r"ModelEmitter\.parts=\[.*\] is invalid: expected a tuple"),
    (dict(parts=(Fallback(), Fallback(floor=0.2))), r"more than one part named \['fallback'\]"),
    (dict(parts=("steering",)), r"'steering' is not a part: it lacks"),
    (dict(acquisition=Threshold(), parts=(Steering(),)), r"Steering\(.*\) needs a ranking acquisition rule"),
    (dict(parts=(Recorder(), dataclasses.replace(EagerRecorder()))), None),
    (dict(parts=(Anchoring(), Anchoring("always"))), r"more than one part named \['anchoring'\]"),
])
def test_a_chain_that_cannot_work_is_refused_naming_the_part(kwargs, match):
    kwargs = {"acquisition": Diverse(), **kwargs}
    if match is None:  # distinct names and metrics: accepted
        ModelEmitter(IsoLine(), **kwargs)
        return
    with pytest.raises(ValueError, match=match):
        ModelEmitter(IsoLine(), **kwargs)


def test_parts_whose_metrics_clash_are_refused():
    @dataclasses.dataclass(frozen=True)
    class Loud(Part):
        name = "loud"

        def metrics(self):
            return {"model_loss": jnp.float32}

    with pytest.raises(ValueError, match=r"the metrics \['model_loss'\] are declared by more than one"):
        ModelEmitter(IsoLine(), Diverse(), parts=(Loud(),))
