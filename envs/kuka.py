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

Two physics backends run the same MjModel behind one interface,
`rollout(ctrl [..., H, nu], mask [...]) -> (final qpos, sensor readings
at every step, finite)`:

* `CRollout` ("mujoco", for CPUs): C MuJoCo through `mujoco.rollout` (one MjData
  per CPU thread), called from inside the jitted generation with
  `jax.pure_callback` on the whole batch at once (`vmap_method="expand_dims"`: a
  vmap over seeds also becomes one call). Rows outside the mask are not simulated.
* `MjxRollout` ("mjx", for accelerators): `mjx.step` in a `lax.scan`, vmapped
  over the batch; fully traced, so masked rows are simulated and ignored.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import functools
import io
import os
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

# mujoco.mjx prints "Failed to import warp: ..." (and mujoco_warp) when the optional MuJoCo Warp is not installed;
# that is expected on a CPU, so the message is held back and anything else it prints passes through.
with contextlib.redirect_stdout(io.StringIO()) as _printed:
    from mujoco import mjx, rollout
sys.stdout.write("".join(line for line in _printed.getvalue().splitlines(keepends=True)
                         if not line.startswith(("Failed to import warp", "Failed to import mujoco_warp"))))

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


class CRollout:
    """C MuJoCo rollouts of a batch of control sequences (the actuators' targets) from the scene's start
    state."""

    def __init__(self, scene: str, q_start: np.ndarray) -> None:
        self.model = load(scene)
        data = start_data(self.model, q_start)
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.initial_state = np.zeros(mujoco.mj_stateSize(self.model, spec))
        mujoco.mj_getState(self.model, data, self.initial_state, spec)
        self.sensors_start = np.array(data.sensordata, np.float32)
        self.datas = [mujoco.MjData(self.model) for _ in range(os.cpu_count() or 1)]

    def __call__(self, ctrl: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """ctrl [..., H, nu], mask [...] -> final qpos [..., nq], sensors [..., H, ns], finite [...]."""
        lead, horizon = ctrl.shape[:-2], ctrl.shape[-2]
        ctrl = np.asarray(ctrl, np.float64).reshape(-1, *ctrl.shape[-2:])
        rows = np.flatnonzero(np.broadcast_to(np.asarray(mask), lead).reshape(-1))
        nq, ns = self.model.nq, self.model.nsensordata
        qpos = np.zeros((ctrl.shape[0], nq), np.float32)
        sensors = np.zeros((ctrl.shape[0], horizon, ns), np.float32)
        finite = np.zeros(ctrl.shape[0], bool)
        if len(rows):
            state, sensors[rows] = rollout.rollout(self.model, self.datas, self.initial_state[None], ctrl[rows])
            qpos[rows] = state[:, -1, 1:1 + nq]
            finite[rows] = np.isfinite(state[:, -1]).all(axis=1)
        return qpos.reshape(*lead, nq), sensors.reshape(*lead, horizon, ns), finite.reshape(lead)


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


# MuJoCo Warp's buffers: contacts per world (a cube on a table touches at up to 8 points; pads and shelves
# add some) and constraint rows per world (contacts with friction, joint limits, the pads' coupling).
WARP_CONTACTS_PER_WORLD = 64
WARP_CONSTRAINTS_PER_WORLD = 512


class MjxRollout:
    """MJX rollouts of a batch of control sequences from the scene's start state (traced; same controls).

    `impl`: "jax" (MJX's JAX implementation: any JAX device) or "warp" (MuJoCo
    Warp through MJX: NVIDIA GPUs, and Warp's CPU device; needs the `gpu` extra).
    """

    def __init__(self, scene: str, q_start: np.ndarray, impl: str = "jax") -> None:
        model = load(scene)
        data = start_data(model, q_start)
        self.impl = impl
        self.model = mjx.put_model(model, impl=impl)
        if impl == "warp":
            self._mj_model, self._start = model, data
            # One flat batch of worlds however the rollouts are vmapped (seeds x population): MuJoCo Warp's
            # contact buffer is shared by all worlds of a call, so it is sized for the whole batch.
            self._rollouts = jax.custom_batching.custom_vmap(self._rollouts_flat)
            self._rollouts.def_vmap(self._rollouts_vmap)
        else:
            self.data = mjx.put_data(model, data)
        self.sensors_start = np.array(data.sensordata, np.float32)

    def __call__(self, ctrl: jax.Array, mask: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """ctrl [B, H, nu] -> final qpos [B, nq], sensors [B, H, ns], finite [B]; every row runs."""
        del mask
        if self.impl == "warp":
            return self._rollouts(ctrl)
        return jax.vmap(lambda c: self._one(self.data, c))(ctrl)

    def _one(self, data: mjx.Data, controls: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """One rollout of controls [H, nu] from `data`."""
        def step(d: mjx.Data, u: jax.Array) -> tuple[mjx.Data, jax.Array]:
            d = mjx.step(self.model, d.replace(ctrl=u))
            return d, d.sensordata

        final, sensors = jax.lax.scan(step, data, controls)
        return final.qpos.astype(jnp.float32), sensors.astype(jnp.float32), jnp.isfinite(final.qpos).all()

    def _rollouts_flat(self, ctrl: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """MuJoCo Warp: ctrl [N, H, u] as one batch of N worlds, with contact and constraint room for all N."""
        worlds = ctrl.shape[0]
        data = mjx.make_data(self._mj_model, impl="warp", naconmax=WARP_CONTACTS_PER_WORLD * worlds,
                             njmax=WARP_CONSTRAINTS_PER_WORLD).replace(
            qpos=jnp.asarray(self._start.qpos, jnp.float32), qvel=jnp.asarray(self._start.qvel, jnp.float32),
            ctrl=jnp.asarray(self._start.ctrl, jnp.float32))
        return jax.vmap(lambda c: self._one(data, c))(ctrl)

    def _rollouts_vmap(self, axis_size: int, in_batched: list[bool],
                       ctrl: jax.Array) -> tuple[tuple[jax.Array, ...], tuple[bool, ...]]:
        """Under an outer vmap (seeds): the [S, N] rollouts as one flat batch of S x N worlds."""
        if not in_batched[0]:
            ctrl = jnp.broadcast_to(ctrl, (axis_size, *ctrl.shape))
        out = self._rollouts(ctrl.reshape(-1, *ctrl.shape[2:]))
        return tuple(x.reshape(axis_size, -1, *x.shape[1:]) for x in out), (True, True, True)
