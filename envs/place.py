"""Place (paper, "Object Placing Task") on the KUKA iiwa scene with shelves.

The robot starts holding a 5 cm cube between the pads of its gripper (held by
friction alone: `envs/assets/gripper.xml`). An action is 5 via-points `(x, y,
z, gamma, T)`: position of the gripper's tip (site "ee": the palm, just above
the held cube's top face), rotation about the vertical, duration in 4 ms steps
(a minimum: the joints' speed limits may stretch it); bounds: x, y in
kuka.VIA_LOW..VIA_HIGH (the reachable front workspace; a via-point out of reach
makes the rollout invalid), z in [0.1, 0.35], gamma in [-pi/2, pi/2], T in [25,
100]. After the last via-point is reached, the arm is given RELEASE_DELAY steps
to settle there, then the gripper opens and the cube drops; the rollout goes
on until it has come to rest. Behavior: the cube's final (x, y).
Quality: minus the drop, the height the cube lost between the release and its
rest (the paper writes the distance but means that smaller drops are better),
and 0 where it lost none (a cube held pressed onto a surface may rise by a
millimetre when it is let go: a placement with no drop, not a better one).
A held cube that hits a shelf or the table on the way can slip in the hand or
be knocked out of it; a rollout whose cube is not in the hand (within
HELD_TOLERANCE of where the grasp holds it) when it is to be let go is invalid:
it placed nothing. See `envs.manipulation` for what else makes a rollout invalid.

Features (`Task.features`, for M-QD's model), from forward kinematics of the
commanded path: where the cube is let go (x, y), its drop to the surface
beneath (table or shelf), and the path's lowest clearance of the held cube's
bottom over the surfaces beneath it (a cube that strikes a shelf on the way
slips or is knocked out of the hand).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from envs import contact, kuka
from envs.manipulation import SETTLE, Manipulation, _surfaces

VIA_POINTS = 5
T_MIN, T_MAX = 25.0, 100.0
Z_LOW, Z_HIGH = 0.1, 0.35
MOTION_STEPS = 2 * VIA_POINTS * int(T_MAX)
RELEASE_DELAY = 100  # steps (0.4 s) for the arm to settle at the last via-point before the cube is let go
HELD_TOLERANCE = 0.02  # m: a cube farther than this from its place in the grasp has slipped out of the pads


@dataclasses.dataclass(frozen=True, eq=False)
class Place(Manipulation):
    quality_range = (-0.35, 0.0)

    def via_points(self, actions: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        via = actions.reshape(actions.shape[0], VIA_POINTS, 5)
        return via[..., :3], via[..., 3], via[..., 4]

    def features(self, actions: jax.Array) -> jax.Array:
        """[B, 4]: the release point (x, y) in behavior-box units, the drop there and the path's lowest clearance
        (`tool_path`; heights in units of Z_HIGH, clearance clipped to [-1, 1])."""
        start = self._rollout.sensors_start
        below = float(start[2] - start[5]) + _cube_half_size()  # the held cube's bottom below the tool's tip
        path = self.tool_path(actions)
        bottom = path[..., 2] - below - self.surface_below(path[..., :2])  # [B, T]
        release = contact.box_units(path[:, -1, :2], self.behavior_low[:2], self.behavior_high[:2])
        return jnp.concatenate([release, bottom[:, -1:] / Z_HIGH,
                                jnp.clip(bottom.min(axis=1, keepdims=True) / Z_HIGH, -1.0, 1.0)], axis=1)

    def release_step(self, durations: jax.Array) -> jax.Array:
        """[B] int32: the step at which the cube is let go, RELEASE_DELAY after the last via-point is reached."""
        return jnp.clip(jnp.ceil(durations.sum(axis=1)).astype(jnp.int32) + RELEASE_DELAY, 0, self.horizon - 1)

    def gripper_controls(self, durations: jax.Array) -> jax.Array:
        steps = jnp.arange(self.horizon)
        closed = steps < self.release_step(durations)[:, None]
        return jnp.where(closed, kuka.GRIP_CLOSED, kuka.GRIP_OPEN).astype(jnp.float32)[..., None]

    def outcome(self, sensors: jax.Array, durations: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        held_at = jnp.maximum(self.release_step(durations) - 1, 0)[:, None, None]
        ee, cube = jnp.split(jnp.take_along_axis(sensors, held_at, axis=1)[:, 0, :6], 2, axis=1)
        # At the start the arm points down holding the cube, as it does when settled at a via-point, so the
        # start's cube-to-gripper offset is where the grasp holds the cube.
        start = jnp.asarray(self._rollout.sensors_start)
        held = jnp.linalg.norm(cube - ee - (start[3:6] - start[:3]), axis=1) <= HELD_TOLERANCE
        return sensors[:, -1, 3:5], -jnp.maximum(cube[:, 2] - sensors[:, -1, 5], 0.0), held


def _action_box(t_max: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    h = math.pi / 2
    return ((*kuka.VIA_LOW, Z_LOW, -h, min(T_MIN, t_max)) * VIA_POINTS,
            (*kuka.VIA_HIGH, Z_HIGH, h, t_max) * VIA_POINTS)


def make(backend: str = "auto", t_max: float = T_MAX, motion_steps: int = MOTION_STEPS,
         settle: int = RELEASE_DELAY + SETTLE) -> Place:
    """The place task; `t_max`, `motion_steps` and `settle` shorten the horizon for quick checks."""
    return Place(*_action_box(t_max), kuka.TABLE_LOW, kuka.TABLE_HIGH, scene="place", backend=backend,
                 motion_steps=motion_steps, settle=settle)


@dataclasses.dataclass(frozen=True, eq=False)
class Place3D(Place):
    """Place with a 3-D behavior: the cube's final (x, y, z), z in [0, the highest surface's top + the cube's
    size]. Reachable: where the cube's centre is within its half size of resting on the table or a shelf (a
    slab over each surface as thick as the cube); coverage is measured there (`mqd_jax.core.coverage`)."""

    def outcome(self, sensors: jax.Array, durations: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        _, qualities, held = super().outcome(sensors, durations)
        return sensors[:, -1, 3:6], qualities, held

    def reachable(self, points: np.ndarray) -> np.ndarray:
        with jax.ensure_compile_time_eval():  # host side, also where a run's initial state is being traced
            surface = np.asarray(self.surface_below(jnp.asarray(points[..., :2], jnp.float32)))
        above = points[..., 2] - surface
        return (above >= 0.0) & (above <= 2 * _cube_half_size())


def _cube_half_size() -> float:
    model = kuka.load("place")
    return float(model.geom_size[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "object")][2])


def make_3d(backend: str = "auto", t_max: float = T_MAX, motion_steps: int = MOTION_STEPS,
            settle: int = RELEASE_DELAY + SETTLE) -> Place3D:
    """place3d: Place with the cube's final 3-D position as its behavior; options as `make`'s."""
    top = float(max(box[4] for _, box in _surfaces("place")))
    return Place3D(*_action_box(t_max), (*kuka.TABLE_LOW, 0.0),
                   (*kuka.TABLE_HIGH, top + 4 * _cube_half_size()), scene="place", backend=backend,
                   motion_steps=motion_steps, settle=settle)
