"""What the KUKA tasks share: via-point actions through IK, the physics backend, and its rollouts.

A task's action is a sequence of via-points; a subclass says how an action
row becomes via-points (`via_points`), what a scene's gripper is told at each
step (`gripper_controls`: Place's grasp and release) and what behaviors and
qualities the rollouts give, and whether the task's own conditions hold
(`outcome`). Every rollout starts from the scene's start state (arm pointing
down above the table's centre), follows the joint trajectory through the
via-points, each segment stretched where the joints' speed limits need it
(`kuka.speed_limited`), and holds the last one to the end of the horizon:
`motion_steps` for the motion, then `settle` steps for the object to come to
rest.

A rollout is invalid (valid = False) when a via-point is out of the arm's reach
(IK ends farther than `kuka.IK_POSITION_TOLERANCE` from it; not simulated), when
the speed-limited motion does not fit in `motion_steps` (not simulated), when
the simulation diverges, when the arm or its gripper touches the table, a shelf
or the floor at any step (the real iiwa's collision detection would stop it;
such touches press with a median of hundreds of newtons in the rollouts that
have them), when the object ends off the table top, when the
object still moves faster than `REST_SPEED` at the end (it has not come to rest,
so its final position is not yet known), or when the task's outcome says so
(Place: the cube was no longer in the hand when it was to be let go).

`backend`: "mujoco" (C MuJoCo, CPUs), "mjx" (MJX's JAX implementation, any
accelerator), "warp" (MuJoCo Warp through MJX, NVIDIA GPUs; the `gpu` extra)
or "auto" (the default: "mujoco" when `jax.default_backend()` is "cpu", else
"warp" on a CUDA GPU with MuJoCo Warp installed, else "mjx");
`mqd_jax.core.registry.make(name, backend=...)` sets it. A scene whose MJCF asks for
MuJoCo's discrete integrator (Place: a friction grasp) runs on "mujoco" and
"warp" only; MJX's JAX implementation does not have that integrator, and is
refused with a clear error.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from envs import kuka, physics
from mqd_jax.core.task import Region, Task

SETTLE = 250  # steps (1 s) after the motion for the object to come to rest
REST_SPEED = 0.01  # m/s: an object faster than this at the end has not come to rest
# `features`' IK iterations: within 0.05 mm of a rollout's 50 for 90% of random push actions (10x cheaper).
FEATURE_IK_ITERATIONS = 10
FEATURE_PATH_POINTS = 48  # forward-kinematics points per segment of the commanded joint path
# The paper's Table I: final coverage (mean, std) per scene and preset.
PAPER_COVERAGE = {
    "push_cube": {"mqd": (0.828, 0.059), "qd": (0.709, 0.047), "random": (0.216, 0.073)},
    "push_sphere": {"mqd": (0.685, 0.0185), "qd": (0.560, 0.009), "random": (0.171, 0.004)},
    "place": {"mqd": (0.639, 0.034), "qd": (0.524, 0.009), "random": (0.349, 0.001)},
}


def _surfaces(scene: str) -> list[tuple[str, tuple[float, ...]]]:
    """The scene's table and shelves (box geoms named table*/shelf*, from its MJCF): (name, (x_low, y_low,
    x_high, y_high, top))."""
    model = kuka.load(scene)
    out = []
    for g in range(model.ngeom):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or ""
        if name.startswith(("table", "shelf")) and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            (x, y, z), (sx, sy, sz) = map(tuple, (model.geom_pos[g], model.geom_size[g]))
            out.append((name, (x - sx, y - sy, x + sx, y + sy, z + sz)))
    return out


@struct.dataclass
class Plan:
    """What an action batch becomes before any physics: whether IK reached its via-points, the speed-limited
    segment durations, and the controls.

    reached [B], durations [B, V] (steps), fits [B] (the motion ends within motion_steps),
    ctrl [B, horizon, nu].
    """

    reached: jax.Array
    durations: jax.Array
    fits: jax.Array
    ctrl: jax.Array


@dataclasses.dataclass(frozen=True, eq=False)
class Manipulation(Task):
    table_ii_column = "robot"
    paper_seeds = 10

    scene: str = "push_cube"
    backend: str = "auto"
    motion_steps: int = 400  # steps of 4 ms for the whole speed-limited motion
    settle: int = SETTLE

    def __post_init__(self) -> None:
        model = kuka.load(self.scene)
        try:
            backend = physics.resolve(self.backend, model)
        except ValueError as e:
            raise ValueError(f"scene {self.scene!r}: {e}") from None
        q_start = kuka.start_pose(self.scene)
        object.__setattr__(self, "physics", backend)
        object.__setattr__(self, "_kinematics", kuka.Kinematics(model))
        object.__setattr__(self, "_q_start", q_start)
        object.__setattr__(self, "_timestep", float(model.opt.timestep))
        object.__setattr__(self, "_rollout", physics.make(backend, model, kuka.start_data(model, q_start)))

    @property
    def horizon(self) -> int:
        """Steps of every rollout: the motion's budget, then the settling."""
        return self.motion_steps + self.settle

    def via_points(self, actions: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """actions [B, n] -> targets [B, V, 3], gammas [B, V], durations [B, V] (steps)."""
        raise NotImplementedError

    def gripper_controls(self, durations: jax.Array) -> jax.Array | None:
        """[B, horizon, 1]: the gripper's targets (kuka.GRIP_CLOSED / GRIP_OPEN) at every step for
        speed-limited durations [B, V], or None for a scene without a gripper."""
        return None

    def outcome(self, sensors: jax.Array, durations: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Sensors [B, H, ns] (ee_pos, object_pos) and durations [B, V] -> behaviors [B, 2], qualities [B] and
        whether the task's own conditions for a valid rollout hold [B]."""
        raise NotImplementedError

    def plan(self, actions: jax.Array) -> Plan:
        """actions [B, n] -> the Plan: IK through the via-points (each from the last), speed-limited durations,
        and the controls (the joint trajectory, then any gripper's targets)."""
        targets, gammas, durations = self.via_points(actions)
        q_start = jnp.asarray(self._q_start, jnp.float32)

        def one(target: jax.Array, gamma: jax.Array, duration: jax.Array) -> tuple[jax.Array, ...]:
            def solve(q: jax.Array, pose: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, tuple[jax.Array, ...]]:
                q, r = self._kinematics.inverse(q, *pose)
                return q, (q, r)

            _, (q_via, r) = jax.lax.scan(solve, q_start, (target, gamma))
            reached = ((jnp.linalg.norm(r[:, :3], axis=1) <= kuka.IK_POSITION_TOLERANCE).all()
                       & (jnp.abs(r[:, 3:]) <= kuka.IK_AXIS_TOLERANCE).all())
            duration = kuka.speed_limited(q_start, q_via, duration, self._timestep)
            return reached, duration, kuka.joint_trajectory(q_start, q_via, duration, self.horizon)

        reached, durations, arm = jax.vmap(one)(targets, gammas, durations)
        fits = durations.sum(axis=1) <= self.motion_steps
        gripper = self.gripper_controls(durations)
        ctrl = arm if gripper is None else jnp.concatenate([arm, gripper], axis=-1)
        return Plan(reached, durations, fits, ctrl)

    def tool_path(self, actions: jax.Array, points: int = FEATURE_PATH_POINTS,
                  iterations: int = FEATURE_IK_ITERATIONS) -> jax.Array:
        """The tool's positions [B, V * points + 1, 3] along the joint path actions [B, n] command, without physics:
        IK of the via-points (`iterations` each, from the last), `points` forward-kinematics points on each
        linear joint-space segment (the path a rollout's position servos track), the start first."""
        targets, gammas, _ = self.via_points(actions)
        q_start = jnp.asarray(self._q_start, jnp.float32)
        fractions = jnp.arange(1, points + 1, dtype=jnp.float32)[:, None] / points

        def one(target: jax.Array, gamma: jax.Array) -> jax.Array:
            def solve(q: jax.Array, pose: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
                q_next = self._kinematics.inverse(q, *pose, iterations=iterations)[0]
                return q_next, q + fractions * (q_next - q)  # [points, 7]

            _, qs = jax.lax.scan(solve, q_start, (target, gamma))
            qs = jnp.concatenate([q_start[None], qs.reshape(-1, q_start.shape[0])])
            return jax.vmap(lambda q: self._kinematics.forward(q)[0])(qs)

        return jax.vmap(one)(targets, gammas)

    def surface_below(self, xy: jax.Array) -> jax.Array:
        """[...] the height of the highest table or shelf top (`_surfaces`) under points xy [..., 2] (0, the
        table's level, where there is none)."""
        boxes = jnp.asarray([box for _, box in _surfaces(self.scene)], jnp.float32)
        x, y = xy[..., 0, None], xy[..., 1, None]
        over = (boxes[:, 0] <= x) & (x <= boxes[:, 2]) & (boxes[:, 1] <= y) & (y <= boxes[:, 3])
        return jnp.where(over, boxes[:, 4], 0.0).max(axis=-1)

    def rollout_controls(self, actions: jax.Array) -> jax.Array:
        """actions [B, n] -> what the backends take: joint targets and, for a scene with a gripper, its
        targets, [B, horizon, nu]."""
        return self.plan(actions).ctrl

    def evaluate(self, actions: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        return self.evaluate_masked(actions, key, jnp.ones(actions.shape[0], bool))

    def simulate(self, ctrl: jax.Array, mask: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """ctrl [B, horizon, nu], mask [B] -> final qpos [B, nq], sensors [B, horizon, ns], finite [B] on the
        task's backend (C MuJoCo skips the rows outside the mask; MJX runs them all)."""
        return physics.simulate(self._rollout, kuka.load(self.scene), ctrl, mask)

    def evaluate_masked(self, actions: jax.Array, key: jax.Array,
                        mask: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        return self.evaluate_sensors(actions, mask)[:3]

    def evaluate_sensors(self, actions: jax.Array,
                         mask: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
        """`evaluate_masked`'s behaviors, qualities and valid, and the rollouts' sensors [B, horizon, ns]."""
        plan = self.plan(actions)
        runs = mask & plan.reached & plan.fits
        _, sensors, finite = self.simulate(plan.ctrl, runs)
        behaviors, qualities, ok = self.outcome(sensors, plan.durations)
        obj = sensors[:, -1, 3:6]
        low, high = jnp.asarray(kuka.TABLE_LOW), jnp.asarray(kuka.TABLE_HIGH)
        on_table = (obj[:, :2] >= low).all(1) & (obj[:, :2] <= high).all(1) & (obj[:, 2] > 0.0)
        speed = jnp.linalg.norm(obj - sensors[:, -2, 3:6], axis=1) / self._timestep
        untouched = ~kuka.arm_touched(sensors)
        return behaviors, qualities, runs & finite & untouched & on_table & (speed <= REST_SPEED) & ok, sensors

    def layout(self) -> tuple[Region, ...]:
        """The table and any shelves (boxes of the scene named table*/shelf*, from its MJCF), the
        via-points' box (x, y) and the object's start, seen from above."""
        model = kuka.load(self.scene)
        parts = []
        for name, (x0, y0, x1, y1, top) in _surfaces(self.scene):
            label = name.replace("_", " ") + ("" if name == "table" else f" (top {100 * top:.0f} cm)")
            colour = (0.88, 0.8, 0.66) if name == "table" else (0.62, 0.45, 0.28)
            parts.append(Region(label, (x0, y0), (x1, y1), colour=colour))
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")
        r = float(model.geom_size[model.body_geomadr[body]][0])
        (cx, cy) = kuka.TABLE_CENTRE
        return (*parts, Region("via-point box", tuple(self.action_low[:2]), tuple(self.action_high[:2]), filled=False),
                Region("object start", (cx - r, cy - r), (cx + r, cy + r), colour="tab:red"))

    def frames(self, action: np.ndarray, width: int = 320, height: int = 240, every: int = 8) -> np.ndarray:
        """The skill `action` [n] on C MuJoCo (whatever the backend), a frame every `every` steps, seen from the
        front left with the headlight turned up. Needs an OpenGL context (MUJOCO_GL=egl offscreen)."""
        model = kuka.load(self.scene)
        c = (self._rollout if isinstance(self._rollout, physics.CRollout)
             else physics.CRollout(model, kuka.start_data(model, self._q_start)))
        ctrl = np.asarray(self.rollout_controls(jnp.asarray(action, jnp.float32)[None]), np.float64)
        model.vis.headlight.ambient[:] = 0.45
        model.vis.headlight.diffuse[:] = 0.6
        camera = mujoco.MjvCamera()
        camera.lookat[:], camera.distance, camera.azimuth, camera.elevation = (0.6, 0.0, 0.1), 1.6, 150.0, -30.0
        return physics.frames(c, ctrl, width, height, every, camera)

    @property
    def paper_coverage(self) -> dict[str, tuple[float, float]]:
        """Table I of the paper for this scene."""
        return PAPER_COVERAGE.get(self.scene, {})

    def ee_path_length(self, sensors: jax.Array) -> jax.Array:
        """[B] distance travelled by the end effector (the scene's first sensor, "ee_pos")."""
        start = jnp.broadcast_to(jnp.asarray(self._rollout.sensors_start[:3]), (sensors.shape[0], 1, 3))
        ee = jnp.concatenate([start, sensors[:, :, :3]], axis=1)
        return jnp.linalg.norm(jnp.diff(ee, axis=1), axis=-1).sum(axis=1)
