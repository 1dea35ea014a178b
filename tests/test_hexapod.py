"""The hexapod (hexapod_omni, hexapod_uni): its physics on both backends, its outcomes, falls, and its frames."""

import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

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
    # Walking, each foot is in the air part of the cycle: on the floor between a third and five sixths of the time.
    assert np.all((contact[1] > 0.33) & (contact[1] < 0.84))


def test_the_contact_fractions_count_the_steps_with_the_foot_down(walked):
    _, _, (contact, _, _), sensors = walked
    down = sensors[:, :, hexapod.FEET][..., 2::3] <= hexapod.CONTACT_HEIGHT
    np.testing.assert_allclose(contact, down.mean(axis=1), atol=1e-6)


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
    actions, (xy, quality, valid), _, _ = walked
    task = hexapod.omni(backend="mjx", seconds=1.0)
    mjx_xy, mjx_quality, mjx_valid = optimized_jit(task.evaluate)(actions, KEY)
    np.testing.assert_allclose(mjx_xy, xy, atol=1e-3)  # measured: 2e-6 m after a second of walking
    np.testing.assert_allclose(mjx_quality[1:], quality[1:], atol=1e-3)
    np.testing.assert_array_equal(mjx_valid, valid)


def test_a_walking_skill_renders_the_robot_moving():
    try:
        mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 8, 8).close()
    except Exception as e:  # no OpenGL context on this machine
        pytest.skip(f"no OpenGL context for MuJoCo's renderer (set MUJOCO_GL=egl): {e}")
    task = hexapod.uni(backend="mujoco", seconds=1.0)
    frames = task.frames(hexapod.TRIPOD, 64, 48, every=25)
    assert frames.shape == (task.horizon // 25, 48, 64, 3) and frames.dtype == np.uint8
    assert frames.mean() > 40 and np.abs(frames[0].astype(int) - frames[-1].astype(int)).mean() > 0.5
