import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.obstacle2d import Obstacle2D
from mqd_jax import Task, run_mqd
from mqd_jax.core import registry


@dataclasses.dataclass(frozen=True, eq=False)
class Faulty(Obstacle2D):
    """2D Obstacle whose rollouts fail on known actions: NaN behavior, inf quality or valid = False."""

    def evaluate(self, actions, key):
        b, q, v = super().evaluate(actions, key)
        b = jnp.where(nan_behavior(actions)[:, None], jnp.nan, b)
        q = jnp.where(inf_quality(actions), jnp.inf, q)
        return b, q, v & ~invalid(actions)


def nan_behavior(a):
    return a[..., 0] > 0.5


def inf_quality(a):
    return a[..., 1] > 0.5


def invalid(a):
    return a[..., 0] < -0.5


def fails(a):
    return nan_behavior(a) | inf_quality(a) | invalid(a)


FAULTY = Faulty(*dataclasses.astuple(registry.make("obstacle2d"))[:4])


@pytest.mark.parametrize("algorithm", ["qd", "mqd"])
def test_failed_rollouts_are_counted_but_never_stored(algorithm, tiny):
    cfg = tiny(task=FAULTY, algorithm=algorithm, warmup_samples=64, num_batches=20)
    state, m = run_mqd(jax.random.PRNGKey(0), cfg)
    invalid_count = np.asarray(m["invalid"])
    # Uniform first-generation actions fail ~60% of the time; children of stored skills rarely do.
    assert invalid_count[0] > 0.3 * cfg.population_size
    outcomes = m["added"] + m["replaced"] + m["rejected"] + m["dropped_full"] + m["invalid"]
    np.testing.assert_array_equal(outcomes, m["evaluations"])  # counted as evaluations
    rep, arch = state.repertoire, state.archive
    assert not fails(np.asarray(rep.actions[:int(rep.count)])).any()
    stored = min(int(arch.total), arch.qualities.shape[0])
    assert not fails(np.asarray(arch.actions[:stored])).any()
    assert np.isfinite(np.asarray(rep.behaviors)).all() and np.isfinite(np.asarray(rep.qualities)).all()
    if algorithm == "mqd":  # the model trains on the repertoire only, so it stays finite
        assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(state.emitter.surrogate.model.params))


@dataclasses.dataclass(frozen=True, eq=False)
class Broken(Task):
    out: str = "ok"

    def evaluate(self, actions, key):
        b, q, v = actions[:, :2], actions[:, 0], jnp.ones(actions.shape[0], bool)
        return {
            "behaviors_1d": lambda: (b[:, 0], q, v),
            "behaviors_int": lambda: (b.astype(jnp.int32), q, v),
            "qualities_2d": lambda: (b, q[:, None], v),
            "valid_float": lambda: (b, q, v.astype(jnp.float32)),
            "two_outputs": lambda: (b, q),
            "raises": lambda: (actions @ jnp.ones(5), q, v),
        }[self.out]()


@pytest.mark.parametrize("out, message", [
    ("behaviors_1d", r"must return \(behaviors \[16, 2\] float.*got"),
    ("behaviors_int", r"must return .*int32\[16, 2\]"),
    ("qualities_2d", r"qualities \[16\] float.*float32\[16, 1\]"),
    ("valid_float", r"valid \[16\] bool"),
    ("two_outputs", r"must return \(behaviors"),
    ("raises", r"evaluate\(actions \[16, 3\], key\) failed"),
])
def test_a_task_with_wrong_outputs_is_refused_at_the_first_call(out, message, tiny):
    task = Broken((0.0,) * 3, (1.0,) * 3, (0.0, 0.0), (1.0, 1.0), out)
    with pytest.raises(ValueError, match=message):
        run_mqd(jax.random.PRNGKey(0), tiny(task=task))
