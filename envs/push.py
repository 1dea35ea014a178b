"""PushCube and PushSphere (paper, "Object Pushing Task") on the KUKA iiwa scene.

An action is 2 via-points `(x, y, gamma, T)`: end-effector position (z fixed
at the object's centre height), rotation about the vertical, and duration in
time steps of 4 ms; bounds: x, y in kuka.VIA_LOW..VIA_HIGH (the arm's reachable front
workspace over the table; a via-point outside the reach makes the rollout
invalid), gamma in [-pi/2, pi/2], T in [25, 150] (a minimum: the joints'
speed limits may stretch it). The arm starts pointing down 0.25 m above the
object at the table's centre, moves through the via-points with its gripper
closed, then holds while the object comes to rest. Behavior: the object's final
(x, y) on the 0.8 x 1.2 m table. Quality: minus the distance the end effector
travelled. See `envs.manipulation` for what makes a rollout invalid.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from envs import kuka
from envs.manipulation import SETTLE, Manipulation

VIA_POINTS = 2
T_MIN, T_MAX = 25.0, 150.0
# Steps for the speed-limited motion: twice the longest requested one (longer motions are invalid).
MOTION_STEPS = 2 * VIA_POINTS * int(T_MAX)


@dataclasses.dataclass(frozen=True, eq=False)
class Push(Manipulation):
    height: float = 0.025  # the object's centre above the table: the via-points' z

    quality_range = (-3.0, 0.0)

    def via_points(self, actions: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        via = actions.reshape(actions.shape[0], VIA_POINTS, 4)
        targets = jnp.concatenate([via[..., :2], jnp.full((*via.shape[:2], 1), self.height)], axis=-1)
        return targets, via[..., 2], via[..., 3]

    def outcome(self, sensors: jax.Array, durations: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        return sensors[:, -1, 3:5], -self.ee_path_length(sensors), jnp.ones(sensors.shape[0], bool)


def make(scene: str, height: float, backend: str = "auto", t_max: float = T_MAX,
         motion_steps: int = MOTION_STEPS, settle: int = SETTLE) -> Push:
    """A push task; `t_max`, `motion_steps` and `settle` shorten the horizon for quick checks."""
    h = math.pi / 2
    low = (*kuka.VIA_LOW, -h, min(T_MIN, t_max)) * VIA_POINTS
    high = (*kuka.VIA_HIGH, h, t_max) * VIA_POINTS
    return Push(low, high, kuka.TABLE_LOW, kuka.TABLE_HIGH, scene=scene, height=height, backend=backend,
                motion_steps=motion_steps, settle=settle)


def cube(backend: str = "auto") -> Push:
    """PushCube (registered as "push_cube")."""
    return make("push_cube", 0.025, backend=backend)


def sphere(backend: str = "auto") -> Push:
    """PushSphere (registered as "push_sphere")."""
    return make("push_sphere", 0.03, backend=backend)
