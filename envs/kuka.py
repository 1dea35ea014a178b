"""The KUKA LBR iiwa 14 scenes: kinematics and inverse kinematics read from the MjModel, joint trajectories
through end-effector via-points, and rollouts on C MuJoCo.

Scenes are MJCF files in `envs/assets/` (`iiwa14.xml` is the robot,
`table.xml` the table and floor; a scene includes both and adds
objects). The platform's top and the table's top are at z = 0; the table spans
x in [0.25, 1.05], y in [-0.6, 0.6]. At the start the end effector (site "ee",
the tip of a closed gripper) points down, 0.25 m above the table's centre.

Joint trajectories keep the datasheet's joint-speed limits: a segment between
via-points lasts at least as long as its slowest joint needs (`speed_limited`).

Forward kinematics is the body chain of the MjModel (body offsets, joint axes,
site offset), written in JAX so that inverse kinematics (damped least squares,
a fixed number of iterations, joint limits enforced) runs for a whole batch of
via-points inside the jitted generation; the same MjModel drives the physics, so
there is one source of truth.

The scenes run on the physics backends of `envs.physics` (`physics.CRollout`,
`physics.MjxRollout`) from `start_data`.
"""

from __future__ import annotations

import concurrent.futures
import functools
import os

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

ASSETS = os.path.join(os.path.dirname(__file__), "assets")
TABLE_LOW, TABLE_HIGH = (0.25, -0.6), (1.05, 0.6)
TABLE_CENTRE = (0.65, 0.0)
# The via-points' (x, y) box: the front workspace the gripper reaches pointing down over the table (parts of it,
# near the base and at the far corners, are out of reach: IK says so, and the rollout is invalid).
VIA_LOW, VIA_HIGH = (0.3, -0.55), (0.8, 0.55)
START_HEIGHT = 0.25
IK_ITERATIONS = 50
IK_DAMPING = 0.05
# A via-point is reached when IK ends within 5 mm of it and its axes within ~3 degrees of pointing down at
# gamma; a farther one is out of the arm's reach (PyRep's IK would raise), and its rollout is invalid.
IK_POSITION_TOLERANCE = 0.005
IK_AXIS_TOLERANCE = 0.05
# KUKA LBR iiwa 14 R820 datasheet, deg/s; trajectories plan at SPEED_MARGIN of them, so that the servos'
# catching up after a lag stays within them.
JOINT_SPEED_LIMITS = (85.0, 85.0, 100.0, 75.0, 130.0, 135.0, 135.0)
SPEED_MARGIN = 0.9
# Pointing down, gamma = 0: the end effector's z axis is the world's -z and its x axis the world's -x
# (the arm leaning forward over the table, flange unturned).
_DOWN = np.diag([-1.0, 1.0, -1.0])
# Scenes whose tool carries a gripper (an asset attached to body "tool"; MJCF cannot add a child to a body of
# an included file). Its servo "gripper_grip" takes the pads' opening: GRIP_CLOSED, 2 cm inside a held 5 cm
# cube, saturates the servo's force limit (a squeeze that does not depend on the object's exact width);
# GRIP_OPEN leaves 3 cm on each side.
GRIPPERS = {"place": "gripper.xml"}
GRIP_CLOSED, GRIP_OPEN = -0.02, 0.03
GRASP_STEPS = 100  # steps (0.4 s) for a grasp to settle before a rollout starts
# The sensors every scene reads, in this order: "ee_pos" (iiwa14.xml), the scene's "object_pos", then the arm's
# touch sensors, which `load` adds: one contact sensor (data "found": its number of contacts) for every pair of
# a geom of the arm (the subtree of link1, gripper included) and a geom of the world body (table, shelves, floor)
# that can collide. The real iiwa's collision detection stops the arm when it feels such a touch, so a rollout
# in which the arm touches the world is invalid (`envs.manipulation`). One sensor per geom pair because MJX
# matches contact sensors by geom only (not by body or subtree).
ARM_TOUCH = slice(6, None)


@functools.cache
def load(scene: str) -> mujoco.MjModel:
    """The MjModel of `envs/assets/<scene>.xml`, with GRIPPERS[scene] attached to the tool and the arm's touch
    sensors added last (cached: one per scene)."""
    spec = mujoco.MjSpec.from_file(os.path.join(ASSETS, f"{scene}.xml"))
    if scene in GRIPPERS:
        gripper = mujoco.MjSpec.from_file(os.path.join(ASSETS, GRIPPERS[scene]))
        spec.attach(gripper, frame=spec.body("tool").add_frame(), prefix="gripper_")
    model = spec.compile()
    if model.nsensordata != ARM_TOUCH.start:
        raise ValueError(f"scene {scene!r}: expected the sensors ee_pos [3] and object_pos [3] only")
    for arm, world in arm_world_pairs(model):
        spec.add_sensor(type=mujoco.mjtSensor.mjSENS_CONTACT, objtype=mujoco.mjtObj.mjOBJ_GEOM, objname=arm,
                        reftype=mujoco.mjtObj.mjOBJ_GEOM, refname=world, intprm=[1, 0, 1])  # found, no reduction
    return spec.compile()


def arm_touched(sensors: jax.Array) -> jax.Array:
    """Sensor readings [B, H, ns] -> [B]: whether the arm touched the world at any step (an ARM_TOUCH sensor
    counted a contact)."""
    return (sensors[:, :, ARM_TOUCH] > 0).any(axis=(1, 2))


def arm_world_pairs(model: mujoco.MjModel) -> list[tuple[str, str]]:
    """The (arm geom, world geom) name pairs that can collide: a geom of a body below link1 (the gripper's
    included) and a geom of the world body whose contype and conaffinity match either way."""
    link0 = model.body("link0").id
    arm = [g for g in range(model.ngeom)
           if model.geom_bodyid[g] > link0 and model.body_rootid[model.geom_bodyid[g]] == link0]
    world = [g for g in range(model.ngeom) if model.geom_bodyid[g] == 0]
    contype, conaffinity = model.geom_contype, model.geom_conaffinity
    pairs = [(model.geom(a).name, model.geom(w).name) for a in arm for w in world
             if contype[a] & conaffinity[w] or contype[w] & conaffinity[a]]
    if not all(a and w for a, w in pairs):
        raise ValueError(f"every arm or world geom that can collide needs a name (for its touch sensor): {pairs}")
    return pairs


class Kinematics:
    """Forward and inverse kinematics of the arm, from an MjModel's body chain to site "ee"."""

    def __init__(self, model: mujoco.MjModel) -> None:
        site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "ee")
        chain, body = [], int(model.site_bodyid[site])
        while body != 0:
            chain.append(body)
            body = int(model.body_parentid[body])
        self.bodies: list[tuple[np.ndarray, np.ndarray, np.ndarray | None, int]] = []
        joint_ids = []
        for b in reversed(chain):
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, model.body_quat[b])
            axis, qadr = None, -1
            if model.body_jntnum[b]:
                j = int(model.body_jntadr[b])
                if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE or np.any(model.jnt_pos[j]):
                    raise ValueError("the arm's chain must be hinges at their bodies' origins")
                axis, qadr = np.array(model.jnt_axis[j]), int(model.jnt_qposadr[j])
                joint_ids.append(j)
            self.bodies.append((np.array(model.body_pos[b]), rot.reshape(3, 3), axis, qadr))
        self.site_pos = np.array(model.site_pos[site])
        self.joints = [qadr for *_, qadr in self.bodies if qadr >= 0]
        self.low = np.asarray(model.jnt_range[joint_ids, 0], np.float32)
        self.high = np.asarray(model.jnt_range[joint_ids, 1], np.float32)

    def frames(self, q: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
        """q [7] -> end-effector position [3], rotation [3, 3], joint axes [7, 3] and joint origins
        [7, 3], all in the world frame."""
        pos, rot = jnp.zeros(3), jnp.eye(3)
        axes, origins = [], []
        for offset, frame, axis, qadr in self.bodies:
            pos, rot = pos + rot @ offset, rot @ frame
            if axis is not None:
                axes.append(rot @ axis)
                origins.append(pos)
                rot = rot @ _axis_rotation(jnp.asarray(axis, jnp.float32), q[self.joints.index(qadr)])
        return pos + rot @ self.site_pos, rot, jnp.stack(axes), jnp.stack(origins)

    def forward(self, q: jax.Array) -> tuple[jax.Array, jax.Array]:
        """q [7] -> end-effector position [3] and rotation matrix [3, 3] (world frame)."""
        return self.frames(q)[:2]

    def residual_and_jacobian(self, q: jax.Array, target: jax.Array,
                              gamma: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The residual [9]: position error, and the errors of the end effector's z and x axes against
        pointing down rotated by gamma about the vertical (axis differences, unlike a rotation vector,
        have no stationary point at a half-turn error); and its Jacobian [9, 7], from the joint axes
        (turning joint i moves a point v by a_i x (v - o_i) and turns an axis u by a_i x u)."""
        pos, rot, axes, origins = self.frames(q)
        want = _axis_rotation(jnp.array([0.0, 0.0, 1.0]), gamma) @ _DOWN
        r = jnp.concatenate([pos - target, rot[:, 2] - want[:, 2], rot[:, 0] - want[:, 0]])
        jac = jnp.concatenate([jnp.cross(axes, pos - origins), jnp.cross(axes, rot[:, 2]),
                               jnp.cross(axes, rot[:, 0])], axis=1).T
        return r, jac

    def inverse(self, q0: jax.Array, target: jax.Array, gamma: jax.Array,
                iterations: int = IK_ITERATIONS) -> tuple[jax.Array, jax.Array]:
        """Joint angles [7] for one pose, from q0, and the final residual [9].

        Damped least squares for a fixed number of `iterations` within the joint
        limits: deterministic, and an unreachable target ends at a nearby
        reachable pose whose residual says how far it is.
        """
        def step(_: int, q: jax.Array) -> jax.Array:
            r, jac = self.residual_and_jacobian(q, target, gamma)
            dq = jnp.linalg.solve(jac.T @ jac + IK_DAMPING ** 2 * jnp.eye(jac.shape[1]), jac.T @ r)
            return jnp.clip(q - dq, self.low, self.high)

        q = jax.lax.fori_loop(0, iterations, step, q0)
        return q, self.residual_and_jacobian(q, target, gamma)[0]


def _axis_rotation(axis: jax.Array, angle: jax.Array) -> jax.Array:
    """Rodrigues: rotation by `angle` about the unit `axis`."""
    k = jnp.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return jnp.eye(3) + jnp.sin(angle) * k + (1.0 - jnp.cos(angle)) * (k @ k)


@functools.cache
def start_pose(scene: str) -> np.ndarray:
    """Joint angles [7] with the end effector pointing down, START_HEIGHT above the table's centre."""
    kin = Kinematics(load(scene))
    seed = jnp.array([0.0, 0.5, 0.0, -1.5, 0.0, 1.1, 0.0])
    target = jnp.array([*TABLE_CENTRE, START_HEIGHT])
    # A task may first be built while a run is being traced; JAX's tracing state is per thread, so
    # solving on a thread of our own gives concrete values.
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        q, r = pool.submit(jax.jit(kin.inverse), seed, target, jnp.float32(0.0)).result()
    if np.abs(np.asarray(r)).max() > 1e-4:
        raise RuntimeError(f"the start pose of {scene} is not reachable (residual {np.asarray(r)})")
    return np.asarray(q, np.float64)


def speed_limited(q_start: jax.Array, q_via: jax.Array, durations: jax.Array, timestep: float) -> jax.Array:
    """durations [V] (steps) stretched so that no joint moves faster than SPEED_MARGIN x its datasheet limit
    along the linear joint-space segments from q_start [7] through q_via [V, 7]."""
    steps = jnp.abs(jnp.diff(jnp.concatenate([q_start[None], q_via]), axis=0))  # [V, 7] rad
    limits = jnp.deg2rad(jnp.asarray(JOINT_SPEED_LIMITS)) * SPEED_MARGIN * timestep  # rad per step
    return jnp.maximum(durations, (steps / limits).max(axis=1))


def joint_trajectory(q_start: jax.Array, q_via: jax.Array, durations: jax.Array, horizon: int) -> jax.Array:
    """Joint targets [horizon, 7]: linear in joint space from q_start through q_via [V, 7].

    Via-point i is reached `durations[:i+1].sum()` steps in (durations may be
    fractional); the last is held to the horizon.
    """
    ends = jnp.cumsum(durations)
    starts = ends - durations
    t = jnp.arange(1, horizon + 1, dtype=jnp.float32)[:, None]
    progress = jnp.clip((t - starts) / jnp.maximum(durations, 1e-6), 0.0, 1.0)  # [H, V]
    steps = jnp.diff(jnp.concatenate([q_start[None], q_via]), axis=0)  # [V, 7]
    return q_start + progress @ steps


def start_data(model: mujoco.MjModel, q_start: np.ndarray) -> mujoco.MjData:
    """MjData at the start: the arm at q_start and holding it, everything else as in the MJCF; a scene with
    a gripper starts with its object squeezed between the pads (placed there, the pads closed on it, and
    GRASP_STEPS simulated so that the grasp has settled)."""
    data = mujoco.MjData(model)
    data.qpos[:7] = q_start
    data.ctrl[:7] = q_start
    mujoco.mj_forward(model, data)
    grip = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, "gripper_grip")
    if grip >= 0:
        tool, adr = model.body("tool").id, object_qpos_address(model)
        depth = model.body("gripper_pad_left").pos  # the pads' centre in the tool's frame
        data.qpos[adr:adr + 3] = data.xpos[tool] + data.xmat[tool].reshape(3, 3) @ depth
        data.qpos[adr + 3:adr + 7] = data.xquat[tool]
        data.ctrl[grip] = GRIP_CLOSED
        mujoco.mj_forward(model, data)
        for _ in range(GRASP_STEPS):
            mujoco.mj_step(model, data)
        data.time = 0.0
    return data


def object_qpos_address(model: mujoco.MjModel) -> int:
    """Where the free joint of the body "object" starts in qpos (its position, then its quaternion)."""
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")
    return int(model.jnt_qposadr[model.body_jntadr[body]])
