import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from envs import arena2d
from envs.object2d import OBJECT_RADIUS, OBJECT_START
from mqd_jax.core import registry


def _action(*subs):
    return np.asarray([np.concatenate(subs)], np.float32)


def test_straight_motion_and_full_quality():
    task = registry.make("obstacle2d")
    # Left for 2 steps from (0.5, 0.1): x decreases by 2 * DT, quality 1 (straight line).
    a = _action([-1, 0, 2], [0, 0, 0], [0, 0, 0])
    b, q, valid = task.evaluate(a)
    np.testing.assert_allclose(b[0], [0.5 - 2 * arena2d.DT, 0.1], atol=1e-6)
    assert valid[0] and q[0] == pytest.approx(1.0)


def test_fractional_duration_is_continuous():
    task = registry.make("obstacle2d")
    b, _, _ = task.evaluate(_action([1, 0, 2.5], [0, 0, 0], [0, 0, 0]))
    np.testing.assert_allclose(b[0], [0.5 + 2.5 * arena2d.DT, 0.1], atol=1e-6)


def test_walls_and_obstacles_block_and_agent_slides():
    task = registry.make("obstacle2d")
    # Up from the start hits the block at y = 0.2 (x = 0.5 is inside its x-span).
    b, _, _ = task.evaluate(_action([0, 1, 10], [0, 0, 0], [0, 0, 0]))
    np.testing.assert_allclose(b[0], [0.5, 0.2], atol=1e-6)
    # Diagonal into the block: y stops at the face, x keeps moving (sliding).
    b, _, _ = task.evaluate(_action([0.2, 1, 10], [0, 0, 0], [0, 0, 0]))
    assert b[0, 1] == pytest.approx(0.2) and b[0, 0] > 0.5 + 0.05
    # Far down: stops at the wall y = 0.
    b, _, _ = task.evaluate(_action([0, -1, 10], [0, 0, 0], [0, 0, 0]))
    np.testing.assert_allclose(b[0], [0.5, 0.0], atol=1e-6)


def test_obstacles_touching_a_wall_are_sealed_to_it():
    task = registry.make("obstacle2d")
    # Right to the wall x = 1, then up along it: the wall piece (0.65-1, 0.5-0.55) stops the agent at y = 0.5
    # (it used to slide through the piece's end on the wall and reach (1, 1)).
    b, _, _ = task.evaluate(_action([1, 0, 10], [0, 1, 10], [0, 1, 10]))
    np.testing.assert_allclose(b[0], [1.0, 0.5], atol=1e-6)
    # The same along the left wall, and the way back down from above is blocked too.
    b, _, _ = task.evaluate(_action([-1, 0, 10], [0, 1, 10], [0, 1, 10]))
    np.testing.assert_allclose(b[0], [0.0, 0.5], atol=1e-6)
    # The shortest path to a point above the wall on the wall's edge goes through the gap, not along the edge:
    # by hand: start -> the block's corner (0.6, 0.2) -> the gap's corner (0.65, 0.55) -> (1, 0.6).
    expected = np.hypot(0.1, 0.1) + np.hypot(0.05, 0.35) + np.hypot(0.35, 0.05)
    assert float(task.shortest_path(np.asarray([[1.0, 0.6]], np.float32))[0]) == pytest.approx(expected, rel=1e-5)
    # Brute force over random actions, step by step: the wall's band y 0.5-0.55 is crossed only in the gap.
    rng = np.random.default_rng(0)
    actions = rng.uniform(task.action_low, task.action_high, (500, task.action_dim)).astype(np.float32)
    times = np.arange(31, dtype=np.float32)
    pos, _, _ = task.evaluate(np.concatenate([arena2d.truncated(a, times) for a in actions]))
    pos = pos.reshape(len(actions), len(times), 2)
    crossed = (pos[:, :-1, 1] <= 0.5) != (pos[:, 1:, 1] <= 0.5)
    x = pos[:, 1:, 0]
    assert crossed.any() and not np.any(crossed & ((x < 0.35) | (x > 0.65)))


def test_detour_has_quality_below_one_and_geodesic_is_exact():
    task = registry.make("obstacle2d")
    # Around the block above the start: right, up past it, then left to above its centre.
    a = _action([1, 0, 3], [0, 1, 5], [-1, 0, 3])
    b, q, _ = task.evaluate(a)
    np.testing.assert_allclose(b[0], [0.5, 0.35], atol=1e-6)
    path = 3 * arena2d.DT + 5 * arena2d.DT + 3 * arena2d.DT
    # Shortest path, by hand: start -> corner (0.6, 0.2) -> along the face to corner
    # (0.6, 0.25) -> (0.5, 0.35).
    shortest = np.hypot(0.1, 0.1) + 0.05 + np.hypot(0.1, 0.1)
    assert float(task.shortest_path(b)[0]) == pytest.approx(shortest, rel=1e-5)
    assert q[0] == pytest.approx(shortest / path, rel=1e-5) and q[0] < 1


def test_never_moving_has_quality_one():
    for name in ("obstacle2d", "object2d"):
        task = registry.make(name)
        _, q, _ = task.evaluate(np.zeros((1, task.action_dim), np.float32))
        assert q[0] == 1.0


def test_object_is_pushed_in_the_push_direction():
    # The hand-computed case starts the agent below the object (the task's own start is a corner).
    task = dataclasses.replace(registry.make("object2d"), agent_start=(0.5, 0.2))
    idle = [0, 0, 0]
    # Straight up from (0.5, 0.2) into the object at (0.5, 0.5): it moves up only.
    b, q, _ = task.evaluate(_action([0, 1, 10], [0, 1, 4], idle, idle, idle))
    assert b[0, 1] > OBJECT_START[1] + 0.05
    assert b[0, 0] == pytest.approx(OBJECT_START[0], abs=1e-6)
    assert q[0] == pytest.approx(1.0, abs=1e-5)
    # Missing it: the object stays where it was.
    b, _, _ = task.evaluate(_action([1, 0, 4], [0, 1, 10], idle, idle, idle))
    np.testing.assert_allclose(b[0], OBJECT_START, atol=1e-7)
    assert np.all(b >= OBJECT_RADIUS - 1e-6)


def test_numpy_and_jax_paths_agree():
    for name in ("obstacle2d", "object2d"):
        task = registry.make(name)
        a = np.random.default_rng(0).uniform(task.action_low, task.action_high, (64, task.action_dim))
        a = a.astype(np.float32)
        bn, qn, _ = task.evaluate(a)
        bj, qj, _ = task.evaluate(jnp.asarray(a))
        np.testing.assert_allclose(bn, np.asarray(bj), atol=1e-5)
        np.testing.assert_allclose(qn, np.asarray(qj), atol=1e-4)
