"""The KUKA push tasks on the C MuJoCo backend (CPU)."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from compiled import compiled
from mujoco import rollout

from envs import kuka, physics
from mqd_jax import Config, run_mqd
from mqd_jax.core import registry


@pytest.fixture(scope="module")
def cube():
    return registry.make("push_cube")


def test_forward_kinematics_is_mujocos():
    model = kuka.load("push_cube")
    kin, data = kuka.Kinematics(model), mujoco.MjData(model)
    for q in np.random.default_rng(0).uniform(-1.5, 1.5, (5, 7)):
        data.qpos[:7] = q
        mujoco.mj_forward(model, data)
        pos, rot = kin.forward(jnp.asarray(q, jnp.float32))
        np.testing.assert_allclose(pos, data.site_xpos[0], atol=1e-5)
        np.testing.assert_allclose(np.asarray(rot).ravel(), data.site_xmat[0], atol=1e-5)


def test_ik_reaches_reachable_targets_pointing_down(cube):
    rng = np.random.default_rng(1)
    n = 64
    targets = np.c_[rng.uniform(0.45, 0.75, n), rng.uniform(-0.25, 0.25, n), rng.uniform(0.02, 0.3, n)]
    gammas = rng.uniform(-np.pi / 2, np.pi / 2, n)
    kin = kuka.Kinematics(kuka.load("push_cube"))
    q0 = jnp.asarray(kuka.start_pose("push_cube"), jnp.float32)
    q, _ = jax.jit(jax.vmap(kin.inverse, in_axes=(None, 0, 0)))(q0, jnp.asarray(targets, jnp.float32),
                                                                 jnp.asarray(gammas, jnp.float32))
    pos, rot = jax.vmap(kin.forward)(q)
    assert np.linalg.norm(np.asarray(pos) - targets, axis=1).max() < 0.01
    down = -np.asarray(rot)[:, 2, 2]  # z axis . (0, 0, -1)
    assert down.min() > np.cos(np.radians(1.0))
    yaw = np.arctan2(-np.asarray(rot)[:, 1, 0], -np.asarray(rot)[:, 0, 0])  # gamma = 0: x axis along -x
    np.testing.assert_allclose(yaw, gammas, atol=np.radians(1.0))
    assert np.all((np.asarray(q) >= np.asarray(kin.low)) & (np.asarray(q) <= np.asarray(kin.high)))


def test_physics_sanity(cube):
    actions = jnp.array([[0.45, 0.25, 0.0, 100, 0.5, 0.25, 0.0, 100],  # stays away from the cube
                         [0.5, 0.0, 0.0, 60, 0.75, 0.0, 0.0, 100]], jnp.float32)  # pushes it along +x
    b, q, valid = jax.jit(cube.evaluate)(actions, None)
    b = np.asarray(b)
    np.testing.assert_allclose(b[0], kuka.TABLE_CENTRE, atol=1e-3)  # untouched: stays put
    assert b[1, 0] - kuka.TABLE_CENTRE[0] > 0.1 and abs(b[1, 1]) < 0.02  # moved in the push direction
    assert np.all(np.asarray(valid)) and np.all(np.asarray(q) < 0)


@pytest.mark.parametrize("task", ["push_cube", "push_sphere", "place"])
def test_run_mqd_on_a_robot_task_inserts_skills_and_grows_coverage(task):
    cfg = Config(task=task, algorithm="qd", population_size=16, max_generations=4, capacity=128,
                 archive_capacity=64)
    state, m = run_mqd(jax.random.PRNGKey(0), cfg)
    cov = np.asarray(m["coverage"])
    assert int(state.repertoire.count) > 2 and cov[-1] > cov[0]
    b = np.asarray(state.repertoire.behaviors[:int(state.repertoire.count)])
    assert np.all((b >= kuka.TABLE_LOW) & (b <= kuka.TABLE_HIGH))


def test_a_vmapped_run_makes_one_rollout_call_per_generation():
    from envs import push

    task = push.make("push_cube", 0.025, backend="mujoco")
    calls = []
    inner = task._rollout

    def counting(ctrl, mask):
        calls.append(ctrl.shape)
        return inner(ctrl, mask)

    counting.sensors_start = inner.sensors_start
    object.__setattr__(task, "_rollout", counting)
    cfg = Config(task=task, population_size=8, max_generations=2, capacity=64, archive_capacity=16)
    jax.vmap(lambda k: run_mqd(k, cfg))(jax.random.split(jax.random.PRNGKey(0), 3))
    assert calls == [(3, 8, task.horizon, 7)] * 2  # all seeds' rollouts in one call per generation


@pytest.mark.parametrize("backend", ["mjx", "warp"])
def test_the_backends_agree_with_c_mujoco_on_pushes_and_on_the_arm_touching_the_table(backend, optimized_jit):
    # Pushes: untouched, and a push along +x 12 mm off the cube's centre line. Measured: equal, and within 1 cm
    # (the contact solvers differ: MJX in float32 with its own collision routines). A push exactly on the
    # centre line is an unstable equilibrium: C MuJoCo keeps its symmetry to 1e-11, MJX's float32 breaks it
    # and the cube ends 1.7 cm aside; a glancing sweep that knocks the cube sideways diverged by 4 cm, so the
    # check uses clean pushes. A touch: a push with its via-points 5 mm below the table's top presses the tool
    # on the table from its first via-point on (the touch sensors are MuJoCo contact sensors per geom pair,
    # which MJX implements; by body or subtree it would not). All three rows are one simulation a backend:
    # MJX compiles a program for ~40 s on this CPU, and `evaluate` judges outcomes and touches from the
    # sensors alike on every backend, so the backends are compared on `simulate`. Short horizon.
    # MuJoCo Warp runs on Warp's CPU device here (its kernels compile for about 90 s the first time).
    from envs import push

    if backend == "warp" and not physics.warp_installed():
        pytest.skip("MuJoCo Warp is not installed (pip install -e .[gpu])")
    pushes = jnp.array([[0.45, 0.25, 0.0, 40, 0.5, 0.25, 0.0, 40],
                        [0.5, 0.012, 0.0, 30, 0.75, 0.012, 0.0, 50]], jnp.float32)
    touch = pushes[:1]
    out = {}
    for name in ("mujoco", backend):
        over, below = (push.make("push_cube", height, backend=name, t_max=50, motion_steps=340, settle=120)
                       for height in (0.025, -0.005))
        assert over.physics == name

        def simulate(pushes, touch, over=over, below=below):
            plans = over.plan(pushes), below.plan(touch)
            _, sensors, finite = over.simulate(jnp.concatenate([p.ctrl for p in plans]), jnp.ones(3, bool))
            return over.outcome(sensors[:2], plans[0].durations)[:2], sensors, finite

        (behaviors, qualities), sensors, finite = optimized_jit(simulate)(pushes, touch)
        out[name] = dict(behaviors=np.asarray(behaviors), qualities=np.asarray(qualities), finite=np.asarray(finite),
                         touched=np.asarray(kuka.arm_touched(sensors)),
                         touches=np.asarray(sensors[2, :, kuka.ARM_TOUCH]).sum(axis=0))  # contact-steps per pair
        if name == "mujoco":  # C MuJoCo's evaluate: the pushes are valid rollouts, the touch makes one invalid
            valid = jax.jit(lambda p, t, over=over, below=below: (over.evaluate(p, None)[2],
                                                                  below.evaluate(t, None)[2]))(pushes, touch)
            np.testing.assert_array_equal(np.concatenate(valid), [True, True, False])
    c, x = out["mujoco"], out[backend]
    assert np.all(c["finite"]) and np.all(x["finite"])
    np.testing.assert_array_equal(c["touched"], [False, False, True])
    np.testing.assert_array_equal(x["touched"], c["touched"])
    assert c["behaviors"][1, 0] - kuka.TABLE_CENTRE[0] > 0.05  # the push moved the cube
    np.testing.assert_allclose(x["behaviors"], c["behaviors"], atol=0.01)
    np.testing.assert_allclose(x["qualities"], c["qualities"], atol=0.01)  # end-effector path lengths, metres
    table = kuka.arm_world_pairs(kuka.load("push_cube")).index(("tool", "table"))
    assert c["touches"][table] > 100 and abs(x["touches"][table] - c["touches"][table]) <= 5
    if backend == "warp":  # vmapped over seeds: one flat batch of worlds, the same rollouts
        b_s, _, v_s = optimized_jit(jax.vmap(lambda a: over.evaluate(a, None)))(jnp.stack([pushes, pushes[::-1]]))
        np.testing.assert_allclose(b_s[0], x["behaviors"], atol=1e-5)
        np.testing.assert_allclose(b_s[1], x["behaviors"][::-1], atol=1e-5)
        assert np.all(v_s)


def test_the_ik_jacobian_is_the_residuals_derivative():
    kin = kuka.Kinematics(kuka.load("push_cube"))
    target, gamma = jnp.array([0.6, 0.1, 0.03]), jnp.float32(0.4)
    for q in np.random.default_rng(2).uniform(-1.5, 1.5, (4, 7)):
        q = jnp.asarray(q, jnp.float32)
        _, jac = kin.residual_and_jacobian(q, target, gamma)
        brute = jax.jacfwd(lambda x: kin.residual_and_jacobian(x, target, gamma)[0])(q)
        np.testing.assert_allclose(jac, brute, atol=1e-5)


def test_a_released_cube_comes_to_rest_on_the_surface_below_and_a_hand_that_touches_it_is_invalid():
    from envs import place

    task = registry.make("place", backend="mujoco")

    def via(x, y, z):
        return [x, y, z, 0.0, 100.0]

    actions = jnp.array([via(0.6, 0.0, 0.25) * 5,  # over the table (top at 0)
                         via(0.7, -0.2, 0.3) * 4 + via(0.7, -0.3, 0.25),  # over the high shelf (top at 0.15)
                         via(0.6, 0.05, 0.25) * 4 + via(0.5, 0.3, 0.2),  # the low shelf (0.08)
                         via(0.6, 0.05, 0.25) * 4 + via(0.5, 0.3, 0.135),  # the cube set down on it
                         via(0.7, -0.2, 0.3) * 4 + via(0.7, -0.3, 0.1)], jnp.float32)  # 5 cm into the high shelf
    ctrl = compiled(task.rollout_controls)(actions)
    qpos, sensors, finite = task._rollout(np.asarray(ctrl), np.ones(5, bool))
    assert np.all(finite)
    cube = qpos[:, kuka.object_qpos_address(task._rollout.model):][:, :3]
    np.testing.assert_allclose(cube[:, 2], [0.025, 0.175, 0.105, 0.105, 0.175], atol=0.003)  # centre 2.5 cm above
    release = np.asarray(task.release_step(task.plan(actions).durations))
    held = sensors[np.arange(5), release - 1, 3:6]  # the cube while still held, just before release
    # The arm has settled at the last via-point before the release (the servos trail a moving target by
    # centimetres; RELEASE_DELAY later they are within millimetres), holding the cube under the gripper.
    np.testing.assert_allclose(held[:4, :2], [[0.6, 0.0], [0.7, -0.3], [0.5, 0.3], [0.5, 0.3]], atol=0.003)
    gripper = sensors[np.arange(4), release[:4] - 1, :3]
    np.testing.assert_allclose(gripper, [[0.6, 0.0, 0.25], [0.7, -0.3, 0.25], [0.5, 0.3, 0.2], [0.5, 0.3, 0.135]],
                               atol=0.003)
    # Let go, a cube drops by its height above the surface (quality minus the drop); set down 2 mm above the
    # shelf (the cube's bottom hangs 5.5 mm below the pads'), it loses none and the pads never touch it. Driven
    # 5 cm into the high shelf, the held cube stops on it and the pads, sliding down the cube, press on the
    # shelf: the iiwa's collision detection would stop that arm, so the rollout is invalid.
    b, q, valid = jax.jit(task.evaluate)(actions, None)
    np.testing.assert_allclose(q, -np.maximum(held[:, 2] - cube[:, 2], 0.0), atol=1e-4)
    assert np.all(np.asarray(q[:3]) < -0.04) and q[3] > -0.004
    # Driven into the shelf, the arm stalls above and the cube stays in the hand: let go, it loses no height
    # (quality 0, whatever the validity).
    assert sensors[4, release[4] - 1, 2] > 0.19 and abs(held[4, 2] - cube[4, 2]) < 0.002 and q[4] > -0.002
    np.testing.assert_allclose(b, cube[:, :2], atol=1e-5)  # at rest: the last two steps agree to 10 um
    touches = sensors[:, :, kuka.ARM_TOUCH].sum(axis=2).max(axis=1)
    assert touches[:4].tolist() == [0, 0, 0, 0] and touches[4] >= 1
    # Brute force: the touch sensors count the contacts, read step by step, between a geom of the arm (the
    # bodies below link1, the gripper's included) and a geom of the world body.
    model, data = task._rollout.model, mujoco.MjData(task._rollout.model)
    arm = {b for b in range(model.body("link1").id, model.nbody) if model.body_rootid[b] == model.body("link0").id}
    for row in range(5):
        mujoco.mj_setState(model, data, task._rollout.initial_state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        for t in range(ctrl.shape[1]):
            data.ctrl[:] = ctrl[row, t]
            mujoco.mj_step(model, data)
            bodies = model.geom_bodyid[np.stack([data.contact.geom1, data.contact.geom2])]
            count = sum(bool({int(a), int(b)} & arm) and 0 in (a, b) for a, b in bodies.T)
            assert count == sensors[row, t, kuka.ARM_TOUCH].sum()
    assert place.VIA_POINTS == 5 and np.asarray(valid).tolist() == [True, True, True, True, False]


def test_the_grasp_holds_the_cube_by_friction_and_a_shelf_can_knock_it_out():
    from envs import place

    task = registry.make("place", backend="mujoco")
    model = task._rollout.model
    assert model.neq == 1 and model.eq_type[0] == mujoco.mjtEq.mjEQ_JOINT  # the pads' coupling; no weld

    def via(x, y, z, gamma=0.0):
        return [x, y, z, gamma, 25.0]

    # A fast tour through the air, turning the gripper (the joints at their speed limits, the gripper at up to
    # 0.8 m/s), then a path that sweeps the held cube low through the high shelf's side (x = 0.6 at y = -0.3,
    # top at 0.15).
    tour = via(0.5, 0.2, 0.3) + via(0.7, 0.2, 0.3, 1.2) + via(0.5, -0.2, 0.3, -1.2) + via(0.7, -0.2, 0.3)
    actions = jnp.array([tour + via(0.55, 0.2, 0.25),
                         via(0.45, -0.3, 0.12) * 2 + via(0.75, -0.3, 0.12) + via(0.5, 0.2, 0.25) * 2], jnp.float32)
    plan = compiled(task.plan)(actions)
    assert np.all(np.asarray(plan.reached & plan.fits))
    _, sensors, _ = task._rollout(np.asarray(plan.ctrl), np.ones(2, bool))
    start = task._rollout.sensors_start
    release = np.asarray(task.release_step(plan.durations))
    in_hand = np.linalg.norm(sensors[:, :, 3:6] - sensors[:, :, :3] - (start[3:6] - start[:3]), axis=-1)
    assert in_hand[0, :release[0]].max() < 0.008  # held through the tour (soft contacts creep a few mm)
    assert in_hand[1, release[1] - 1] > place.HELD_TOLERANCE  # knocked out before it was let go
    _, _, valid = jax.jit(task.evaluate)(actions, None)
    assert np.asarray(valid).tolist() == [True, False]  # a cube lost on the way placed nothing
    with pytest.raises(ValueError, match=r"discrete integrator .* use backend='mujoco' \(CPUs\) or 'warp'"):
        registry.make("place", backend="mjx")


def test_trajectories_keep_the_datasheets_joint_speed_limits(cube):
    # By hand: joint 4 (75 deg/s) turning 1 rad needs 1 / (75 deg/s x SPEED_MARGIN x 4 ms) steps; a longer
    # requested duration is kept.
    q0, via = jnp.zeros(7), jnp.zeros((2, 7)).at[0, 3].set(1.0).at[1, 3].set(1.0)
    need = 1.0 / (np.radians(75.0) * kuka.SPEED_MARGIN * 0.004)
    np.testing.assert_allclose(kuka.speed_limited(q0, via, jnp.array([25.0, 30.0]), 0.004), [need, 30.0], rtol=1e-5)
    # Brute force: the simulated joints of random pushes never exceed the datasheet's speeds.
    rng = np.random.default_rng(3)
    actions = jnp.asarray(rng.uniform(cube.action_low, cube.action_high, (16, cube.action_dim)), jnp.float32)
    plan = cube.plan(actions)
    rows = np.flatnonzero(np.asarray(plan.reached & plan.fits))
    c = cube._rollout
    state, _ = rollout.rollout(c.model, c.datas, c.initial_state[None], np.asarray(plan.ctrl, np.float64)[rows])
    qvel = state[:, :, 1 + c.model.nq:1 + c.model.nq + 7]
    assert len(rows) >= 8 and np.all(np.abs(qvel).max(axis=(0, 1)) <= np.radians(kuka.JOINT_SPEED_LIMITS))


def test_unreachable_via_points_and_objects_still_moving_make_a_rollout_invalid():
    from envs import push

    # (0.3, 0, table height) is inside the arm's reach limit (too close to its base); (0.5, 0) is reachable.
    actions = jnp.array([[0.3, 0.0, 0.0, 50, 0.5, 0.0, 0.0, 50],
                         [0.5, 0.0, 0.0, 30, 0.75, 0.0, 0.0, 50]], jnp.float32)
    ball = registry.make("push_sphere", backend="mujoco")
    plan = ball.plan(actions)
    assert not bool(plan.reached[0]) and bool(plan.reached[1])
    _, _, valid = jax.jit(ball.evaluate)(actions, None)
    assert np.asarray(valid).tolist() == [False, True]  # the pushed ball came to rest in the settling time
    # The same push with no time to settle: the ball is still rolling at the end, so the rollout is invalid.
    motion = int(np.ceil(float(plan.durations[1].sum())))
    hasty = push.make("push_sphere", 0.03, backend="mujoco", motion_steps=motion, settle=5)
    _, _, valid = jax.jit(hasty.evaluate)(actions[1:], None)
    assert not bool(valid[0])


def test_the_warp_backend_without_mujoco_warp_is_refused_with_the_extra_to_install(monkeypatch):
    from envs import push

    monkeypatch.setattr(physics, "warp_installed", lambda: False)
    with pytest.raises(ValueError, match=r"backend='warp' needs MuJoCo Warp: pip install -e \.\[gpu\]"):
        push.make("push_cube", 0.025, backend="warp")
    assert physics.auto_backend() == "mujoco"  # on a CPU
