"""PushCube and PushSphere (paper, "Object Pushing Task") on the KUKA iiwa scene.

An action is 2 via-points `(x, y, gamma, T)`: end-effector position on the
table (z fixed at the object's centre height), rotation about the vertical, and
duration in time steps of 4 ms; bounds: x in [0.4, 0.8], y in [-0.3, 0.3],
gamma in [-pi/2, pi/2], T in [25, 150]. The arm starts pointing down 0.25 m
above the object at the table's centre, moves through the via-points (joint
targets from IK, linear in joint space), then holds for 100 steps; the horizon
is 400 steps. Behavior: the object's final (x, y). Quality: minus the distance
the end effector travelled. An object that leaves the table, or a simulation
that diverges, gives valid = False.
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


@dataclasses.dataclass(frozen=True, eq=False)
class Push(Manipulation):
    height: float = 0.025  # the object's centre above the table: the via-points' z

    quality_range = (-3.0, 0.0)

    def via_points(self, actions: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        via = actions.reshape(actions.shape[0], VIA_POINTS, 4)
        targets = jnp.concatenate([via[..., :2], jnp.full((*via.shape[:2], 1), self.height)], axis=-1)
        return targets, via[..., 2], via[..., 3]

    def outcome(self, qpos: jax.Array, sensors: jax.Array, durations: jax.Array) -> tuple[jax.Array, jax.Array]:
        return qpos[:, 7:9], -self.ee_path_length(sensors)


def make(scene: str, height: float, backend: str = "auto", t_max: float = T_MAX, settle: int = SETTLE) -> Push:
    """A push task; `t_max` and `settle` shorten the horizon for quick checks."""
    (x0, y0), (x1, y1) = kuka.REACH_LOW, kuka.REACH_HIGH
    h = math.pi / 2
    low = (x0, y0, -h, min(T_MIN, t_max)) * VIA_POINTS
    high = (x1, y1, h, t_max) * VIA_POINTS
    return Push(low, high, kuka.TABLE_LOW, kuka.TABLE_HIGH, scene=scene, height=height, backend=backend,
                horizon=VIA_POINTS * math.ceil(t_max) + settle)


def cube(backend: str = "auto") -> Push:
    """PushCube (registered as "push_cube")."""
    return make("push_cube", 0.025, backend=backend)


def sphere(backend: str = "auto") -> Push:
    """PushSphere (registered as "push_sphere")."""
    return make("push_sphere", 0.03, backend=backend)
