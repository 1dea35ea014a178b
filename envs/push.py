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

Features (`Task.features`, for M-QD's model): where the tool's commanded path
meets the object and where it would sweep it (`envs.contact`), and the path's
length, from forward kinematics; a path point can touch when the tool's tip is
below the object's top.

Auxiliary outputs (`Task.auxiliary`, what a rollout observes on the way):
"moved", +1 if the object ever got farther than MOVED from its start (the tool
touched it), else -1; "moved_at", the fraction of the horizon at which it first
did, from [0, 1] to [-1, 1] (1 if never); and the object's (x, y) at a quarter,
half and three quarters of the motion, in behavior-box units.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco

from envs import contact, kuka
from envs.manipulation import SETTLE, Manipulation

VIA_POINTS = 2
T_MIN, T_MAX = 25.0, 150.0
MOVED = 0.005  # m: an object this far from its start has been moved (touched)
# Steps for the speed-limited motion: twice the longest requested one (longer motions are invalid).
MOTION_STEPS = 2 * VIA_POINTS * int(T_MAX)


@dataclasses.dataclass(frozen=True, eq=False)
class Push(Manipulation):
    height: float = 0.025  # the object's centre above the table: the via-points' z

    quality_range = (-3.0, 0.0)
    auxiliary = ("moved", "moved_at", "x_1/4", "y_1/4", "x_1/2", "y_1/2", "x_3/4", "y_3/4")

    def via_points(self, actions: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        via = actions.reshape(actions.shape[0], VIA_POINTS, 4)
        targets = jnp.concatenate([via[..., :2], jnp.full((*via.shape[:2], 1), self.height)], axis=-1)
        return targets, via[..., 2], via[..., 3]

    def features(self, actions: jax.Array) -> jax.Array:
        """[B, 12]: `envs.contact.path_contact` and `swept` of the tool's path (`tool_path`) against the object's
        start, within the object's half-width plus the tool's radius, and the path's length (the quality's
        distance, as commanded) mapped from [0, 3] m to [-1, 1]."""
        model = kuka.load(self.scene)
        size = lambda name: float(model.geom_size[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)][0])  # noqa: E731
        path = self.tool_path(actions)
        args = (path[..., :2], path[..., 2] < 2.0 * self.height, kuka.TABLE_CENTRE, size("object") + size("tool"),
                self.behavior_low, self.behavior_high)
        length = jnp.linalg.norm(jnp.diff(path, axis=1), axis=-1).sum(axis=1)  # minus the quality, as commanded
        return jnp.concatenate([contact.path_contact(*args), contact.swept(*args),
                                (2.0 * length / -self.quality_range[0] - 1.0)[:, None]], axis=1)

    def evaluate_with_auxiliary(self, actions: jax.Array, key: jax.Array,
                                mask: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
        behaviors, qualities, valid, sensors = self.evaluate_sensors(actions, mask)
        obj = sensors[..., 3:5]  # [B, H, 2]
        moving = jnp.linalg.norm(obj - jnp.asarray(kuka.TABLE_CENTRE, jnp.float32), axis=-1) > MOVED
        moved = moving.any(axis=1)
        at = jnp.where(moved, jnp.argmax(moving, axis=1) / (obj.shape[1] - 1), 1.0)
        times = [int(self.motion_steps * f) for f in (0.25, 0.5, 0.75)]
        way = contact.box_units(obj[:, times], self.behavior_low, self.behavior_high).reshape(obj.shape[0], -1)
        return behaviors, qualities, valid, jnp.concatenate(
            [jnp.where(moved, 1.0, -1.0)[:, None], 2.0 * at[:, None] - 1.0, way], axis=1).astype(jnp.float32)

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
