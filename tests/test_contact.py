"""What a task tells the model beyond the action (`Task.features`, `Task.auxiliary`) and the gate that learns
the auxiliary outputs (`mqd_jax.surrogate.gate`): hand-computed features, features against the rollouts they
anticipate, the protocol's checks, the gate's null outcome, and the promise that a task without features or
auxiliary outputs runs exactly as without them."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiled import compiled

from envs import arena2d, contact, push
from mqd_jax import Surrogate, Task, run_mqd
from mqd_jax.core import registry
from mqd_jax.core import run as run_lib
from mqd_jax.core import state as state_lib
from mqd_jax.core.task import check_outputs, check_task
from mqd_jax.surrogate import model
from mqd_jax.surrogate.gate import Gate


def test_path_contact_of_a_straight_path_through_the_disk_and_of_one_that_misses_it():
    # Along y = 0 from x = 0 to 1 in steps of 0.1, past a disk of radius 0.15 at (0.5, 0): the first point within
    # reach is x = 0.4, the path goes on 0.6 after it; the box is [0, 1] x [-1, 1] (half-diagonal sqrt(5) / 2).
    xs = jnp.linspace(0.0, 1.0, 11)
    through = jnp.stack([xs, jnp.zeros(11)], axis=1)
    miss = jnp.stack([xs, jnp.full(11, 0.5)], axis=1)
    f = np.asarray(contact.path_contact(jnp.stack([through, miss]), jnp.ones((2, 11), bool), (0.5, 0.0), 0.15,
                                        (0.0, -1.0), (1.0, 1.0)))
    half_diagonal = np.sqrt(5.0) / 2
    np.testing.assert_allclose(f[0], [1.0, -1.0, 2 * 0.4 - 1, 0.0, 1.0, 0.0, 0.6 / half_diagonal - 1, 1.0, 0.0],
                               atol=1e-6)
    # The miss: closest approach 0.5 (of [0, 4] reaches), no touch: the end as touch point, no direction.
    np.testing.assert_allclose(f[1], [-1.0, 0.5 / 0.15 / 2 - 1, 1.0, 0.5, 0.0, 0.0, -1.0, 1.0, 0.5], atol=1e-6)
    # A point that cannot touch (an arm's tool held above the object) counts as far.
    above = np.asarray(contact.path_contact(through[None], jnp.zeros((1, 11), bool), (0.5, 0.0), 0.15, (0.0, -1.0),
                                            (1.0, 1.0)))
    assert above[0, 0] == -1.0


def test_the_2d_tasks_features_anticipate_their_rollouts():
    obstacle, obj = registry.make("obstacle2d"), registry.make("object2d")
    a = jax.random.uniform(jax.random.PRNGKey(0), (256, obstacle.action_dim), minval=jnp.asarray(obstacle.action_low),
                           maxval=jnp.asarray(obstacle.action_high))
    f = np.asarray(obstacle.features(a))
    b = np.asarray(obstacle.evaluate(a, None)[0])
    # A free path that crosses no obstacle is the rollout's path: it ends where the agent ends (up to a slide along
    # a face the strict crossing test lets pass).
    free = f[:, 2] < 0
    assert 0.3 < free.mean() < 0.9
    assert np.median(np.abs((f[free, :2] + 1) / 2 - b[free])) < 1e-6
    # One that crosses one stops at or before the point before its first crossing... or slides on from there.
    np.testing.assert_allclose(np.asarray(arena2d.free_path(a[:3], obstacle.start))[:, -1], (f[:3, :2] + 1) / 2,
                               atol=1e-6)
    # 2D Object: the object moves exactly when the agent's path (as if the object were not there) comes within
    # reach of it.
    a = jax.random.uniform(jax.random.PRNGKey(1), (512, obj.action_dim), minval=jnp.asarray(obj.action_low),
                           maxval=jnp.asarray(obj.action_high))
    ra = obj.agent_radius
    path = arena2d.free_path(a, obj.agent_start, ra, 1.0 - ra)
    touched = np.asarray(contact.path_contact(path, jnp.ones(path.shape[:2], bool), obj.object_start,
                                              ra + obj.object_radius, obj.behavior_low, obj.behavior_high))[:, 0] > 0
    b, _, _, aux = obj.evaluate_with_auxiliary(a, None)
    moved = np.linalg.norm(np.asarray(b) - np.asarray(obj.object_start), axis=1) > 1e-6
    assert touched.sum() > 10 and np.array_equal(touched, moved)
    np.testing.assert_array_equal(np.asarray(aux)[:, 0], np.where(moved, 1.0, -1.0))  # its auxiliary output


def test_the_pushes_features_and_auxiliary_outputs_agree_with_their_rollouts():
    """Forward kinematics of the commanded path says whether the tool meets the cube; the rollout's "moved" says
    whether the cube moved; on random actions they agree but for grazes."""
    task = push.make("push_cube", 0.025, backend="mujoco")
    a = jax.random.uniform(jax.random.PRNGKey(0), (96, task.action_dim), minval=jnp.asarray(task.action_low),
                           maxval=jnp.asarray(task.action_high))
    b, _, valid, aux = jax.jit(lambda a: task.evaluate_with_auxiliary(a, None, jnp.ones(96, bool)))(a)
    b_plain, _, valid_plain = jax.jit(lambda a: task.evaluate(a, None))(a)
    np.testing.assert_array_equal(b, b_plain)  # the same rollouts
    np.testing.assert_array_equal(valid, valid_plain)
    valid, aux, f = np.asarray(valid), np.asarray(aux), np.asarray(compiled(task.features)(a))
    moved = aux[valid, 0] > 0
    away = np.linalg.norm(np.asarray(b)[valid] - np.asarray(push.kuka.TABLE_CENTRE), axis=1) > push.MOVED
    assert moved.sum() >= 5 and moved[away].all()  # a cube that ends away from its start has moved
    assert (moved == (f[valid, 0] > 0)).mean() >= 0.9
    # "moved_at" is 1 exactly where it never moved; the way-points of a cube that never moved are its start.
    np.testing.assert_array_equal(aux[valid, 1] == 1.0, ~moved)
    np.testing.assert_allclose(aux[valid][~moved, 2:], 0.0, atol=0.02)


@dataclasses.dataclass(frozen=True, eq=False)
class Flick(Task):
    """A flick: the object (behavior) stays at (0.2, 0.2) unless action[0] > 0, when it goes to 0.5 + 0.3 a[1:3];
    the auxiliary output "moved" says which. Quality: 0.5 unmoved, 0.5 + 0.2 a[1] moved."""

    auxiliary = ("moved", "spare")

    def evaluate(self, actions, key):
        return self.evaluate_with_auxiliary(actions, key, jnp.ones(actions.shape[0], bool))[:3]

    def evaluate_with_auxiliary(self, actions, key, mask):
        acts = actions[:, 0] > 0
        b = jnp.where(acts[:, None], 0.5 + 0.3 * actions[:, 1:3], 0.2)
        q = jnp.where(acts, 0.5 + 0.2 * actions[:, 1], 0.5)
        aux = jnp.stack([jnp.where(acts, 1.0, -1.0), actions[:, 2]], axis=1)
        return b, q, jnp.ones(actions.shape[0], bool), aux


def flick():
    return Flick((-1.0,) * 3, (1.0,) * 3, (0.0, 0.0), (1.0, 1.0))


def test_the_gate_learns_which_actions_act_and_predicts_the_null_outcome_for_the_others(linear_task):
    task, gate = flick(), Gate(hidden_size=16, buffer_size=512, batch_size=64, num_batches=400)
    state = gate.init(jax.random.PRNGKey(0), task, task.action_dim)
    x = jnp.linspace(-1, 1, 7)
    # Before both labels were seen it passes everything.
    assert (np.asarray(gate.probability(state, jnp.zeros((3, 3)), task)) == 1.0).all()
    a = jax.random.uniform(jax.random.PRNGKey(1), (256, 3), minval=-1.0, maxval=1.0)
    b, q, _, aux = task.evaluate_with_auxiliary(a, None, None)
    usable = jnp.arange(256) < 250  # the last rows are not usable: not remembered, not in the null outcome
    outcomes = jnp.concatenate([b, q[:, None]], axis=1)
    for i in range(4):
        state = compiled(gate.update)(jax.random.PRNGKey(2 + i), state, a, aux, outcomes, usable, task,
                                      jnp.float32(1e-2))
    unmoved = np.asarray(aux[:250, 0] < 0)
    np.testing.assert_array_equal(np.asarray(state.counts), [4 * unmoved.sum(), 4 * (~unmoved).sum()])
    np.testing.assert_allclose(np.asarray(gate.null(state)), [0.2, 0.2, 0.5], atol=1e-6)
    probe = jnp.stack([x, 0.3 * x, -0.2 * x], axis=1)
    p = np.asarray(gate.probability(state, probe, task))
    assert (p[x > 0.2] > 0.5).all() and (p[x < -0.2] < 0.5).all()
    predictions = jnp.full((1, 7, 3), 0.9)
    gated = np.asarray(gate.gated(state, probe, predictions, task))[0]
    np.testing.assert_allclose(gated[p < 0.5], np.broadcast_to([0.2, 0.2, 0.5], gated[p < 0.5].shape), atol=1e-6)
    np.testing.assert_array_equal(gated[p >= 0.5], np.float32(0.9))
    # A gate's label must be one of the task's auxiliary outputs; a task without any leaves a gate idle.
    with pytest.raises(ValueError, match="not 'touched'"):
        Gate(label="touched").check_task(task)
    Gate().check_task(linear_task)
    assert not Gate().serves(linear_task)


def test_a_run_with_a_gate_and_features_learns_the_flick_and_a_task_without_them_runs_as_without(tiny, linear_task):
    cfg = tiny(task=flick(), algorithm="mqd", gate=True, warmup_samples=32, num_batches=20, max_generations=6)
    state, metrics = run_mqd(jax.random.PRNGKey(0), cfg)
    counts = np.asarray(state.emitter.surrogate.gate.counts)
    assert counts.sum() == int(metrics["num_evaluations"][-1]) and (counts > 0).all()
    # On a task with neither features nor auxiliary outputs both options change nothing, bit for bit.
    runs = [run_mqd(jax.random.PRNGKey(1), tiny(task=linear_task, algorithm="mqd", warmup_samples=32,
                                                 num_batches=20, max_generations=4, **options))
            for options in ({}, {"features": True, "gate": True})]
    for x, y in zip(jax.tree.leaves(runs[0]), jax.tree.leaves(runs[1]), strict=True):
        np.testing.assert_array_equal(x, y)


def test_the_model_takes_the_features_as_inputs_after_the_actions():
    task = registry.make("obstacle2d")
    a = jax.random.uniform(jax.random.PRNGKey(0), (5, task.action_dim))
    x, actions, features = map(np.asarray, compiled(lambda a: (model.inputs(a, task, True), model.normalize_actions(
        a, task), task.features(a)))(a))
    np.testing.assert_array_equal(x[:, :task.action_dim], actions)
    np.testing.assert_array_equal(x[:, task.action_dim:], features)
    state = Surrogate(hidden_size=4, features=True).init(jax.random.PRNGKey(0), task, 64)
    assert state.model.params["params"]["Dense_0"]["kernel"].shape == (1, task.action_dim + 6, 4)


@dataclasses.dataclass(frozen=True, eq=False)
class Broken(Task):
    """A task whose `features` or auxiliary outputs break the protocol (`how`)."""

    how: str = "features"
    auxiliary = ()

    def evaluate(self, actions, key):
        return jnp.zeros((actions.shape[0], 2)), jnp.zeros(actions.shape[0]), jnp.ones(actions.shape[0], bool)

    def features(self, actions):
        return jnp.zeros(actions.shape[0]) if self.how == "features" else super().features(actions)


@dataclasses.dataclass(frozen=True, eq=False)
class Unreturned(Broken):
    auxiliary = ("moved",)


def test_broken_features_and_auxiliary_outputs_are_refused_before_a_run():
    bounds = ((-1.0,) * 3, (1.0,) * 3, (0.0, 0.0), (1.0, 1.0))
    with pytest.raises(ValueError, match=r"features\(actions \[4, 3\]\) must return features \[4, f\]"):
        check_outputs(Broken(*bounds), "broken", 4)
    with pytest.raises(ValueError, match="implement evaluate_with_auxiliary"):
        check_task(Unreturned(*bounds, how="none"), "unreturned")
    with pytest.raises(ValueError, match=r"auxiliary=.* is invalid"):
        check_task(type("Twice", (Flick,), {"auxiliary": ("moved", "moved")})(*bounds), "twice")


def test_tell_needs_the_auxiliary_outputs_of_a_task_that_returns_them(tiny):
    cfg = tiny(task=flick(), algorithm="qd", max_generations=2)
    state = state_lib.init(jax.random.PRNGKey(0), cfg)
    candidates = run_lib.ask(state, cfg)
    b, q, v, aux = flick().evaluate_with_auxiliary(candidates.actions, None, None)
    with pytest.raises(ValueError, match=r"pass auxiliary= \[16, 2\]"):
        run_lib.tell(state, candidates, b, q, v, cfg)
    with pytest.raises(ValueError, match=r"auxiliary has shape \(16, 1\); expected \(16, 2\)"):
        run_lib.tell(state, candidates, b, q, v, cfg, auxiliary=aux[:, :1])
    told, _ = run_lib.tell(state, candidates, b, q, v, cfg, auxiliary=aux)
    assert int(told.generation) == 1
