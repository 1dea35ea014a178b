"""Place (paper, "Object Placing Task") on the KUKA iiwa scene with shelves.

The robot starts holding a 5 cm cube under its gripper (a weld). An action is
5 via-points `(x, y, z, gamma, T)`: gripper-tip position, rotation about the
vertical, duration in 4 ms steps; bounds: x in [0.4, 0.8], y in [-0.3, 0.3], z
in [0.1, 0.35], gamma in [-pi/2, pi/2], T in [25, 100]. When the last via-point
is reached the weld is switched off (the same on both backends: an
eq_active control channel) and the cube falls; 100 settling steps follow
(horizon 600). Behavior: the cube's final (x, y). Quality: minus the drop, the
height the cube lost between release and rest (the paper writes the distance
but means that smaller drops are better). A cube that leaves the table or a
diverging simulation gives valid = False.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from envs import kuka
from envs.manipulation import SETTLE, Manipulation

VIA_POINTS = 5
T_MIN, T_MAX = 25.0, 100.0
Z_LOW, Z_HIGH = 0.1, 0.35


@dataclasses.dataclass(frozen=True, eq=False)
class Place(Manipulation):
    quality_range = (-0.35, 0.0)

    def via_points(self, actions: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        via = actions.reshape(actions.shape[0], VIA_POINTS, 5)
        return via[..., :3], via[..., 3], via[..., 4]

    def release_step(self, durations: jax.Array) -> jax.Array:
        """[B] int32: the step at which the cube is let go (when the last via-point is reached)."""
        return jnp.clip(jnp.ceil(durations.sum(axis=1)).astype(jnp.int32), 0, self.horizon - 1)

    def release_switch(self, durations: jax.Array) -> jax.Array:
        steps = jnp.arange(self.horizon)
        return (steps < self.release_step(durations)[:, None]).astype(jnp.float32)[..., None]

    def outcome(self, qpos: jax.Array, sensors: jax.Array, durations: jax.Array) -> tuple[jax.Array, jax.Array]:
        release = self.release_step(durations)
        z_release = jnp.take_along_axis(sensors[:, :, 5], jnp.maximum(release - 1, 0)[:, None], axis=1)[:, 0]
        return qpos[:, 7:9], -(z_release - qpos[:, 9])


def make(backend: str = "auto", t_max: float = T_MAX, settle: int = SETTLE) -> Place:
    """The place task; `t_max` and `settle` shorten the horizon for quick checks."""
    (x0, y0), (x1, y1) = kuka.REACH_LOW, kuka.REACH_HIGH
    h = math.pi / 2
    low = (x0, y0, Z_LOW, -h, min(T_MIN, t_max)) * VIA_POINTS
    high = (x1, y1, Z_HIGH, h, t_max) * VIA_POINTS
    return Place(low, high, kuka.TABLE_LOW, kuka.TABLE_HIGH, scene="place", backend=backend,
                 horizon=VIA_POINTS * math.ceil(t_max) + settle)
