"""The hexapod (hexapod_omni, hexapod_uni): its physics on both backends, its outcomes, falls, and its frames."""

import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import rollout

from envs import hexapod, physics

KEY = jax.random.PRNGKey(0)
BACKWARD = hexapod.TRIPOD * np.tile(np.array([-1.0, 1.0, 1.0, 1.0], np.float32), len(hexapod.LEGS))


@pytest.fixture(scope="module")
def walked():
    """One second of: standing (the zero action), the tripod gait, and the tripod gait backwards, on C MuJoCo."""
    omni, uni = hexapod.omni(backend="mujoco", seconds=1.0), hexapod.uni(backend="mujoco", seconds=1.0)
    actions = jnp.asarray(np.stack([np.zeros(24, np.float32), hexapod.TRIPOD, BACKWARD]))
    _, sensors, _ = physics.simulate(omni._rollout, hexapod.load(), omni.rollout_controls(actions), jnp.ones(3, bool))
    return actions, omni.evaluate(actions, KEY), uni.evaluate(actions, KEY), np.asarray(sensors)


def test_the_zero_controller_stands_still_and_the_tripod_gait_walks_both_ways(walked):
    _, (xy, _, valid), (contact, forward, valid_uni), sensors = walked
    assert np.asarray(valid).all() and np.asarray(valid_uni).all()
    assert np.abs(xy[0]).max() < 1e-3 and abs(sensors[0, :, 2].min() - sensors[0, :, 2].max()) < 1e-3  # standing
    np.testing.assert_array_equal(contact[0], 1.0)  # every foot on the floor all the time
    assert xy[1, 0] > 0.25 and abs(xy[1, 1]) < 0.05  # the tripod gait: forward, about straight
    assert xy[2, 0] < -0.25 and abs(xy[2, 1]) < 0.05  # its mirror: backward
    np.testing.assert_allclose(forward, xy[:, 0])  # hexapod_uni's quality: the forward distance
    # Walking, each foot is lifted half of each cycle: it touches the floor a fifth to a half of the time.
    assert np.all((contact[1] > 0.2) & (contact[1] < 0.55))


def random_actions(n: int, seed: int) -> np.ndarray:
    low, high = hexapod._box(len(hexapod.LEGS))
    return np.random.default_rng(seed).uniform(low, high, (n, len(low))).astype(np.float32)


def start_state(model: mujoco.MjModel) -> np.ndarray:
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state = np.zeros(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, hexapod.start_data(model), state, spec)
    return state


def test_the_contact_fractions_are_mujocos_contact_list():
    """Stepping C MuJoCo by hand, a foot is down at a step exactly when the step's contact list holds a contact
    between it and the floor; hexapod_uni's behaviors are those steps' shares."""
    task = hexapod.uni(backend="mujoco", seconds=0.6)
    actions = np.concatenate([hexapod.TRIPOD[None], random_actions(3, 0)])
    model = hexapod.load()
    ctrl = np.asarray(task.rollout_controls(jnp.asarray(actions)), np.float64)
    feet = [model.geom(f"{leg}_foot").id for leg in hexapod.LEGS]
    floor = model.geom("floor").id
    down = np.zeros((len(actions), task.horizon, len(feet)), bool)
    for i in range(len(actions)):
        data = hexapod.start_data(model)
        for t in range(task.horizon):
            data.ctrl[:] = ctrl[i, t]
            mujoco.mj_step(model, data)
            touching = {(c.geom1, c.geom2) for c in data.contact[:data.ncon]} if data.ncon else set()
            down[i, t] = [(floor, f) in touching or (f, floor) in touching for f in feet]
    assert 0.05 < down[:, 20:].mean() < 0.95  # feet both up and down after the fade-in
    fractions = np.asarray(task.evaluate(jnp.asarray(actions), KEY)[0])
    np.testing.assert_array_equal(np.round(fractions * task.horizon), down.sum(axis=1))  # step for step


def test_the_servos_are_critically_damped_and_keep_the_mx28s_torque_speed_line():
    """At full command a joint's torque (the servo's, clamped to the stall torque, plus the motor's back-EMF
    damping) is the stall torque falling linearly to 0 at the no-load speed; a 0.5 rad step of a hip settles
    without overshoot, no faster than the no-load speed; random gaits keep their joints within 5% of it."""
    model = hexapod.load()
    data = hexapod.start_data(model)
    hip = model.joint("front_left_hip")
    for share in (0.0, 0.5, 1.0):
        data.qvel[hip.dofadr[0]] = share * hexapod.NO_LOAD_SPEED
        data.ctrl[0] = data.qpos[hip.qposadr[0]] + 1.0  # far ahead: the servo saturates
        mujoco.mj_forward(model, data)
        torque = data.actuator_force[0] + data.qfrc_passive[hip.dofadr[0]]
        # The damping, 0.434 N m s/rad, is stall torque / no-load speed to 3 digits: within 2e-4 N m here.
        assert torque == pytest.approx(hexapod.STALL_TORQUE * (1 - share), abs=5e-4)
    state = start_state(model)
    step = np.zeros((1, 250, model.nu))
    step[..., 0] = 0.5
    states, _ = rollout.rollout(model, mujoco.MjData(model), state[None], step)
    angle, speed = states[0, :, 1 + hip.qposadr[0]], states[0, :, 1 + model.nq + hip.dofadr[0]]
    assert angle[-1] == pytest.approx(0.5, abs=0.01) and angle.max() < 0.5 * 1.02  # overshoot < 2%
    assert np.abs(speed).max() < hexapod.NO_LOAD_SPEED
    task = hexapod.omni(backend="mujoco", seconds=1.5)
    ctrl = np.asarray(task.rollout_controls(jnp.asarray(random_actions(8, 1))), np.float64)
    states, _ = rollout.rollout(model, mujoco.MjData(model), state[None], ctrl)
    assert np.abs(states[:, :, 1 + model.nq + 6:]).max() < 1.05 * hexapod.NO_LOAD_SPEED  # the 12 joints


def test_the_step_is_converged():
    """A 4x finer step (1 ms) moves the final positions of random controllers over 3 s by a median of at most a
    quarter of hexapod_omni's t_dist, and their contact fractions by a median of at most a quarter of
    hexapod_uni's."""
    moved, fractions = hexapod.finer_step_shift(hexapod.load(), random_actions(16, 2))
    assert np.median(moved) <= hexapod.Omni.default_t_dist / 4
    assert np.median(fractions) <= hexapod.Uni.default_t_dist / 4


def test_neighbouring_legs_do_not_overlap():
    """A gait that swings the front legs back onto the middle ones (`ONTO_MIDDLE`): without the legs' collisions
    they overlap by more than 1 cm; with them, never by more than 0.5 mm (MuJoCo's geometric distance)."""
    xml = open(hexapod.XML).read()
    free = xml[:xml.index("  <contact>")] + xml[xml.index("  </contact>") + len("  </contact>"):]

    def deepest_overlap(model):
        data = hexapod.start_data(model)
        horizon = round(1.5 / model.opt.timestep)
        ctrl = np.asarray(hexapod.controls(jnp.asarray(hexapod.ONTO_MIDDLE[None]), horizon, model.opt.timestep))[0]
        deepest = 0.0
        for t in range(horizon):
            data.ctrl[:] = ctrl[t]
            mujoco.mj_step(model, data)
            if t % 2 == 0:
                deepest = max(deepest, hexapod.leg_overlap(model, data))
        return deepest

    assert deepest_overlap(mujoco.MjModel.from_xml_string(free)) > 0.01
    assert deepest_overlap(hexapod.load()) < 5e-4


def test_omni_quality_is_the_heading_error_to_the_circular_arc():
    task = hexapod.omni(backend="mujoco", seconds=0.1)

    def quality(x, y, heading):
        sensors = np.zeros((1, 2, 25), np.float32)
        sensors[:, -1, :2] = (x, y)
        sensors[:, -1, hexapod.TORSO_QUAT] = (math.cos(heading / 2), 0, 0, math.sin(heading / 2))
        return float(task.outcome(jnp.asarray(sensors))[1][0])

    # The arc from the origin (facing +x) through (1, 1) is a quarter circle: at (1, 1) it heads +y.
    assert quality(1.0, 1.0, math.pi / 2) == pytest.approx(0.0, abs=1e-6)
    assert quality(1.0, 1.0, 0.0) == pytest.approx(-0.5, abs=1e-6)
    assert quality(0.5, 0.0, 0.0) == pytest.approx(0.0, abs=1e-6)  # straight ahead, facing ahead
    assert quality(0.5, 0.0, math.pi) == pytest.approx(-1.0, abs=1e-6)  # straight ahead, facing back
    assert quality(0.0, 1.0, math.pi) == pytest.approx(0.0, abs=1e-6)  # a half circle to (0, 1): heading -x
    # Within a millimetre of the start the arc has no direction: the quality is how far the robot turned.
    assert quality(1e-4, 1e-4, 0.0) == pytest.approx(0.0, abs=1e-6)  # the arc's formula would say -0.5
    assert quality(0.0, -5e-4, -math.pi / 4) == pytest.approx(-0.25, abs=1e-6)
    assert quality(2e-3, 2e-3, 0.0) == pytest.approx(-0.5, abs=1e-6)  # beyond it, the arc again


def test_a_fall_is_invalid():
    """The robot dropped on its back (the start state turned over) is flagged invalid, where standing is not."""
    task = hexapod.omni(backend="mujoco", seconds=0.5)
    model = hexapod.load()
    data = hexapod.start_data(model)
    data.qpos[2] = 0.15
    data.qpos[3:7] = (0.0, 1.0, 0.0, 0.0)  # upside down
    upright = task.evaluate(jnp.zeros((1, 24)), KEY)[2]
    object.__setattr__(task, "_rollout", physics.CRollout(model, data))
    fallen = task.evaluate(jnp.zeros((1, 24)), KEY)[2]
    assert bool(upright[0]) and not bool(fallen[0])


def test_mjx_agrees_with_c_mujoco(walked, optimized_jit):
    """Both tasks' outcomes of the same MJX rollouts, the still robot's quality and the feet's contacts with the
    floor (MJX's `contact` sensors) included."""
    actions, (xy, quality, valid), (contact, _, _), _ = walked
    omni, uni = hexapod.omni(backend="mjx", seconds=1.0), hexapod.uni(backend="mjx", seconds=1.0)

    def outcomes(actions):
        _, sensors, finite = physics.simulate(omni._rollout, hexapod.load(), omni.rollout_controls(actions),
                                              jnp.ones(actions.shape[0], bool))
        return omni.outcome(sensors), uni.outcome(sensors)[0], finite

    (mjx_xy, mjx_quality), mjx_contact, finite = optimized_jit(outcomes)(actions)
    np.testing.assert_allclose(mjx_xy, xy, atol=1e-3)  # measured: 2e-5 m after a second of walking
    np.testing.assert_allclose(mjx_quality, quality, atol=1e-3)
    np.testing.assert_allclose(mjx_contact, contact, atol=2.5 / hexapod.uni(seconds=1.0).horizon)  # 2 steps
    assert np.asarray(finite).all() and np.asarray(valid).all()


def test_a_walking_skill_renders_the_robot_moving():
    try:
        mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 8, 8).close()
    except Exception as e:  # no OpenGL context on this machine
        pytest.skip(f"no OpenGL context for MuJoCo's renderer (set MUJOCO_GL=egl): {e}")
    task = hexapod.uni(backend="mujoco", seconds=1.0)
    frames = task.frames(hexapod.TRIPOD, 64, 48, every=25)
    assert frames.shape == (task.horizon // 25, 48, 64, 3) and frames.dtype == np.uint8
    assert frames.mean() > 40 and np.abs(frames[0].astype(int) - frames[-1].astype(int)).mean() > 0.5
