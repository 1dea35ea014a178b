"""Place (paper, "Object Placing Task") on the KUKA iiwa scene with shelves.

The robot starts holding a 5 cm cube under its gripper (a weld). An action is
5 via-points `(x, y, z, gamma, T)`: gripper-tip position (the held cube's
bottom), rotation about the vertical, duration in 4 ms steps (a minimum: the
joints' speed limits may stretch it); bounds: x, y in
kuka.VIA_LOW..VIA_HIGH (the reachable front workspace; a via-point out of reach
makes the rollout invalid), z in [0.1, 0.35], gamma in [-pi/2, pi/2], T in [25,
100]. After the last via-point is reached, the arm is given RELEASE_DELAY steps
to settle there, then the weld is switched off (the same on every backend: an
eq_active control channel) and the cube drops; the rollout goes on until it
has come to rest. Behavior: the cube's final (x, y).
Quality: minus the drop, the height the cube lost between the release and its
rest (the paper writes the distance but means that smaller drops are better),
and 0 where it lost none: a cube let go while the grasp holds it pressed into a
surface rises by a few millimetres when it is let go, which is a placement
with no drop, not a better one (12-15% of the valid rollouts of a run rose).
See `envs.manipulation` for what makes a rollout invalid.
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
MOTION_STEPS = 2 * VIA_POINTS * int(T_MAX)
RELEASE_DELAY = 50  # steps (0.2 s) between reaching the last via-point and letting the cube go


@dataclasses.dataclass(frozen=True, eq=False)
class Place(Manipulation):
    quality_range = (-0.35, 0.0)

    def via_points(self, actions: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        via = actions.reshape(actions.shape[0], VIA_POINTS, 5)
        return via[..., :3], via[..., 3], via[..., 4]

    def release_step(self, durations: jax.Array) -> jax.Array:
        """[B] int32: the step at which the cube is let go, RELEASE_DELAY after the last via-point is reached."""
        return jnp.clip(jnp.ceil(durations.sum(axis=1)).astype(jnp.int32) + RELEASE_DELAY, 0, self.horizon - 1)

    def release_switch(self, durations: jax.Array) -> jax.Array:
        steps = jnp.arange(self.horizon)
        return (steps < self.release_step(durations)[:, None]).astype(jnp.float32)[..., None]

    def outcome(self, sensors: jax.Array, durations: jax.Array) -> tuple[jax.Array, jax.Array]:
        release = self.release_step(durations)
        z_release = jnp.take_along_axis(sensors[:, :, 5], jnp.maximum(release - 1, 0)[:, None], axis=1)[:, 0]
        return sensors[:, -1, 3:5], -jnp.maximum(z_release - sensors[:, -1, 5], 0.0)


def make(backend: str = "auto", t_max: float = T_MAX, motion_steps: int = MOTION_STEPS,
         settle: int = RELEASE_DELAY + SETTLE) -> Place:
    """The place task; `t_max`, `motion_steps` and `settle` shorten the horizon for quick checks."""
    h = math.pi / 2
    low = (*kuka.VIA_LOW, Z_LOW, -h, min(T_MIN, t_max)) * VIA_POINTS
    high = (*kuka.VIA_HIGH, Z_HIGH, h, t_max) * VIA_POINTS
    return Place(low, high, kuka.TABLE_LOW, kuka.TABLE_HIGH, scene="place", backend=backend,
                 motion_steps=motion_steps, settle=settle)
