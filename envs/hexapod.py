"""Hexapod locomotion (Cully et al. 2015; DA-QD, Lim et al. 2022): a six-legged robot with an open-loop periodic
controller, on either physics backend (`envs.physics`).

The robot (`assets/hexapod.xml`): a 24 x 14 x 4 cm torso of 1 kg and six legs
(front, middle, rear; left, right), each a hip that swings the leg forward and
back (yaw) and a knee that lifts the foot; twelve position servos modelled on the
Robotis Dynamixel MX-28 (Cully et al. 2015's): stall torque 2.5 N m, no-load speed
5.76 rad/s, the torque falling linearly with speed between them (a DC motor's
back-EMF), critically damped. Neighbouring legs collide. The limits are in the
datasheet, docs/data/hexapod_datasheet.md (`experiments/bench_hexapod.py --datasheet`).

The step, 4 ms, is converged for the behaviors: a 4x finer step (1 ms) moves the
final positions of random controllers by a median of about 10 mm over 3 s, under a
quarter of hexapod_omni's `t_dist` (5 cm); 0.14's robot at 10 ms: 51 mm
(`experiments/hexapod_fidelity.py`).

An action is four numbers per leg (24, legs in the order front left, middle
left, rear left, front right, middle right, rear right):

* swing s in [-1, 1]: the hip's amplitude, `SWING` * s rad (signed: a negative
  swing walks that leg backwards);
* phase p in [-1, 1]: the leg's phase in the gait cycle, pi * p;
* lift l in [0, 1]: the knee's amplitude, `LIFT` * l rad, raised while the hip
  turns forward when s > 0 (the foot returns through the air and pushes back on
  the ground: the body goes forward), backward when s < 0;
* offset o in [-1, 1]: the hip's mean angle, `OFFSET` * o rad (turns).

    hip(t)  = SWING s sin(2 pi t / PERIOD + pi p) + OFFSET o
    knee(t) = LIFT l max(0, cos(2 pi t / PERIOD + pi p))

both faded in over the first `RAMP` seconds. The zero action stands still; the
tripod gait (`TRIPOD`) walks forward. Every rollout lasts `seconds` (3 s, as in
DA-QD) from the robot standing at the origin, facing +x.

A rollout is invalid (valid = False) when the robot falls (the torso tilts past
`FALL_TILT` from upright, or touches the floor: its centre below
`FALL_HEIGHT`) at any step, or the simulation diverges.

Tasks:

* `hexapod_omni`: behavior = the torso's final (x, y) in [-1.5, 1.5]^2 m; quality =
  -|heading error| / pi in [-1, 0], the angle between the torso's final heading and
  the tangent, at the end point, of the circular arc from the start (facing +x)
  through it (the "omnidirectional" task: a good skill reaches its point
  following a circle, facing where it goes);
  Within `STILL` of the start the arc has no direction: the tangent is the start's
  heading (+x), so a robot that stays put scores how far it turned, -|yaw| / pi;
* `hexapod_uni`: behavior = the six feet's contact-time fractions in [0, 1]^6: the
  share of steps at which the simulator's contact list holds a contact between the
  foot and the floor (a `contact` sensor per foot, on both backends); quality = the
  forward (x) distance in m.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import os

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from envs import physics
from mqd_jax.core.task import Task

XML = os.path.join(os.path.dirname(__file__), "assets", "hexapod.xml")
LEGS = ("front_left", "middle_left", "rear_left", "front_right", "middle_right", "rear_right")
PARAMETERS = 4  # per leg: swing, phase, lift, offset
SWING, LIFT, OFFSET = 0.5, 0.6, 0.3  # rad
PERIOD = 0.5  # s, one gait cycle
RAMP = 0.25  # s over which the controller fades in
SECONDS = 3.0
SETTLE = 0.5  # s the robot stands before a rollout starts (from the MJCF's pose)
FALL_TILT = math.radians(60)
FALL_HEIGHT = 0.04  # m, the torso's centre (it stands at 0.0995)
# The servos: Robotis Dynamixel MX-28 at 12 V (the MJCF's forcerange and joint damping are these).
STALL_TORQUE = 2.5  # N m
NO_LOAD_SPEED = 55 * 2 * math.pi / 60  # rad/s (55 rpm)
STILL = 1e-3  # m from the start within which hexapod_omni's arc has no direction
TORSO_POS, TORSO_QUAT, FEET, CONTACTS = slice(0, 3), slice(3, 7), slice(7, 25), slice(25, 31)  # sensor columns
# Tripod gait: legs 1, 3, 5 (front left, rear left, middle right) against 2, 4, 6; full swing and lift.
TRIPOD = np.array([[1.0, 0.0, 1.0, 0.0], [1.0, 1.0, 1.0, 0.0], [1.0, 0.0, 1.0, 0.0],
                   [1.0, 1.0, 1.0, 0.0], [1.0, 0.0, 1.0, 0.0], [1.0, 1.0, 1.0, 0.0]], np.float32).reshape(-1)
# Neighbouring legs driven into each other: every hip swings fully, the front legs' hips offset back and the
# middle legs' forward, the middle legs swinging against the front ones.
ONTO_MIDDLE = np.array([[1.0, 0.0, 0.0, -1.0], [-1.0, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0],
                        [1.0, 0.0, 0.0, -1.0], [-1.0, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0]], np.float32).reshape(-1)


@functools.cache
def load() -> mujoco.MjModel:
    """The hexapod's MjModel."""
    return mujoco.MjModel.from_xml_path(XML)


def start_data(model: mujoco.MjModel) -> mujoco.MjData:
    """The robot standing at the origin: the MJCF's pose after `SETTLE` seconds with the servos at zero."""
    data = mujoco.MjData(model)
    for _ in range(round(SETTLE / model.opt.timestep)):
        mujoco.mj_step(model, data)
    data.time = 0.0
    return data


def finer_step_shift(model: mujoco.MjModel, actions: np.ndarray, finer: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Per row of actions [B, 24], rolled out for `SECONDS` on C MuJoCo: how far the final (x, y) (m) and the feet's
    contact fractions (Euclidean, as hexapod_uni's behaviors) move when `model`'s step is `finer` times finer."""
    outcomes = []
    for timestep in (model.opt.timestep, model.opt.timestep / finer):
        stepped = copy.copy(model)
        stepped.opt.timestep = timestep
        ctrl = np.asarray(controls(jnp.asarray(actions), round(SECONDS / timestep), timestep))
        _, sensors, _ = physics.CRollout(stepped, start_data(stepped))(ctrl, np.ones(len(actions), bool))
        outcomes.append((sensors[:, -1, :2], (sensors[..., CONTACTS] > 0).mean(axis=1)))
    (xy, fractions), (finer_xy, finer_fractions) = outcomes
    return np.linalg.norm(xy - finer_xy, axis=1), np.linalg.norm(fractions - finer_fractions, axis=1)


def leg_overlap(model: mujoco.MjModel, data: mujoco.MjData) -> float:
    """The deepest overlap (m; 0 if none) of the legs that `assets/hexapod.xml` lets collide (its <pair>s) in `data`
    of `model`: this robot, with its legs' collisions or without them."""
    pairs = load()
    return max(0.0, *(-mujoco.mj_geomDistance(model, data, a, b, 0.05, None)
                      for a, b in zip(pairs.pair_geom1, pairs.pair_geom2, strict=True)))


def controls(actions: jax.Array, steps: int, timestep: float) -> jax.Array:
    """The servos' targets [B, steps, 12] (hip, knee per leg) of actions [B, 24] (see the module's docstring)."""
    a = actions.reshape(actions.shape[0], len(LEGS), PARAMETERS)
    swing, phase, lift, offset = (a[..., i, None] for i in range(PARAMETERS))  # [B, 6, 1]
    t = jnp.arange(1, steps + 1, dtype=jnp.float32) * timestep  # [T]
    angle = 2 * jnp.pi * t / PERIOD + jnp.pi * phase  # [B, 6, T]
    fade = jnp.minimum(t / RAMP, 1.0)
    hip = fade * (SWING * swing * jnp.sin(angle) + OFFSET * offset)
    knee = fade * LIFT * lift * jnp.maximum(0.0, jnp.cos(angle))
    return jnp.stack([hip, knee], axis=-1).transpose(0, 2, 1, 3).reshape(actions.shape[0], steps, 2 * len(LEGS))


def _yaw(quat: jax.Array) -> jax.Array:
    w, x, y, z = (quat[..., i] for i in range(4))
    return jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y**2 + z**2))


def _up(quat: jax.Array) -> jax.Array:
    """The z component of the torso's up axis (1 upright, 0 on its side)."""
    x, y = quat[..., 1], quat[..., 2]
    return 1 - 2 * (x**2 + y**2)


@dataclasses.dataclass(frozen=True, eq=False)
class Hexapod(Task):
    """A hexapod locomotion task; a subclass says what behaviors and qualities the rollouts give (`outcome`)."""

    table_ii_column = "robot"
    paper_seeds = 10
    revision = 1  # 0.15: contacts from the simulator, MX-28 servos, legs that collide, a 4 ms step

    backend: str = "auto"
    seconds: float = SECONDS

    def __post_init__(self) -> None:
        model = load()
        backend = physics.resolve(self.backend, model)
        object.__setattr__(self, "physics", backend)
        object.__setattr__(self, "_rollout", physics.make(backend, model, start_data(model)))

    @property
    def horizon(self) -> int:
        """Steps of every rollout."""
        return round(self.seconds / load().opt.timestep)

    def rollout_controls(self, actions: jax.Array) -> jax.Array:
        """actions [B, 24] -> the servos' targets [B, horizon, 12]."""
        return controls(actions, self.horizon, float(load().opt.timestep))

    def evaluate(self, actions: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        return self.evaluate_masked(actions, key, jnp.ones(actions.shape[0], bool))

    def evaluate_masked(self, actions: jax.Array, key: jax.Array,
                        mask: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        _, sensors, finite = physics.simulate(self._rollout, load(), self.rollout_controls(actions), mask)
        quat = sensors[..., TORSO_QUAT]
        upright = (_up(quat) >= math.cos(FALL_TILT)).all(axis=1) & (sensors[..., 2] >= FALL_HEIGHT).all(axis=1)
        behaviors, qualities = self.outcome(sensors)
        return behaviors, qualities, mask & finite & upright

    def outcome(self, sensors: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Sensors [B, H, 31] (torso position, torso quaternion, six feet's positions, six feet's contacts with
        the floor) -> behaviors [B, d], qualities [B]."""
        raise NotImplementedError

    def frames(self, action: np.ndarray, width: int = 320, height: int = 240, every: int = 10) -> np.ndarray:
        """The skill `action` [24] on C MuJoCo (whatever the backend), a frame every `every` steps, the camera
        following the torso from behind and above. Needs an OpenGL context (MUJOCO_GL=egl offscreen)."""
        model = load()
        c = self._rollout if isinstance(self._rollout, physics.CRollout) else physics.CRollout(model, start_data(model))
        ctrl = np.asarray(self.rollout_controls(jnp.asarray(action, jnp.float32)[None]), np.float64)
        camera = mujoco.MjvCamera()
        camera.distance, camera.azimuth, camera.elevation = 1.2, 210.0, -30.0
        return physics.frames(c, ctrl, width, height, every, camera, follow=True)


@dataclasses.dataclass(frozen=True, eq=False)
class Omni(Hexapod):
    """hexapod_omni: behavior = final (x, y); quality = -|heading error to the circular arc| / pi."""

    quality_range = (-1.0, 0.0)
    default_t_dist = 0.05  # m: a disk of 5 cm radius per skill

    def outcome(self, sensors: jax.Array) -> tuple[jax.Array, jax.Array]:
        xy = sensors[:, -1, :2]
        moved = jnp.linalg.norm(xy, axis=1) > STILL
        # The arc from the origin facing +x through xy, at xy (its start's heading where it has no direction).
        tangent = jnp.where(moved, 2 * jnp.arctan2(xy[:, 1], xy[:, 0]), 0.0)
        error = jnp.angle(jnp.exp(1j * (_yaw(sensors[:, -1, TORSO_QUAT]) - tangent)))  # wrapped to [-pi, pi]
        return xy, -jnp.abs(error) / jnp.pi


@dataclasses.dataclass(frozen=True, eq=False)
class Uni(Hexapod):
    """hexapod_uni: behavior = the six feet's contact-time fractions; quality = forward distance (m)."""

    quality_range = (-2.0, 2.0)  # m in 3 s; the tripod gait walks 1.3
    # Contact fraction. "mqd" fills the default capacity (4,096) late in Table II's 100 x 100 rollouts: raise it
    # to keep every niche (docs/results.md, "The hexapod").
    default_t_dist = 0.15

    def outcome(self, sensors: jax.Array) -> tuple[jax.Array, jax.Array]:
        return (sensors[..., CONTACTS] > 0).mean(axis=1), sensors[:, -1, 0]


def _box(legs: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    return (-1.0, -1.0, 0.0, -1.0) * legs, (1.0, 1.0, 1.0, 1.0) * legs


def omni(backend: str = "auto", seconds: float = SECONDS) -> Omni:
    """hexapod_omni (registered); `seconds` shortens the rollouts for quick checks."""
    return Omni(*_box(len(LEGS)), (-1.5, -1.5), (1.5, 1.5), backend=backend, seconds=seconds)


def uni(backend: str = "auto", seconds: float = SECONDS) -> Uni:
    """hexapod_uni (registered); `seconds` shortens the rollouts for quick checks."""
    return Uni(*_box(len(LEGS)), (0.0,) * len(LEGS), (1.0,) * len(LEGS), backend=backend, seconds=seconds)
