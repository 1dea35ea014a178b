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

`backend` picks the physics: "mujoco" (C MuJoCo, CPUs), "mjx" (MJX,
accelerators) or "auto" (the default: "mujoco" when `jax.default_backend()` is
"cpu", else "mjx"); `envs.make(name, backend=...)` and `Config.physics_backend`
set it.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from envs import kuka
from mqd_jax.task import Task

VIA_POINTS = 2
T_MIN, T_MAX = 25.0, 150.0
SETTLE = 100
BACKENDS = ("auto", "mujoco", "mjx")


@dataclasses.dataclass(frozen=True, eq=False)
class Push(Task):
    scene: str = "push_cube"
    height: float = 0.025  # the object's centre above the table: the via-points' z
    backend: str = "auto"
    horizon: int = VIA_POINTS * int(T_MAX) + SETTLE  # steps of 4 ms

    quality_range = (-3.0, 0.0)

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"backend={self.backend!r} is invalid: expected one of {BACKENDS}")
        backend = self.backend
        if backend == "auto":
            backend = "mujoco" if jax.default_backend() == "cpu" else "mjx"
        q_start = kuka.start_pose(self.scene)
        object.__setattr__(self, "physics", backend)
        object.__setattr__(self, "_kinematics", kuka.Kinematics(kuka.load(self.scene)))
        object.__setattr__(self, "_q_start", q_start)
        rollout = kuka.CRollout if backend == "mujoco" else kuka.MjxRollout
        object.__setattr__(self, "_rollout", rollout(self.scene, q_start))

    def controls(self, actions: jax.Array) -> jax.Array:
        """actions [B, 8] -> joint targets [B, horizon, 7] (IK through the via-points)."""
        via = actions.reshape(actions.shape[0], VIA_POINTS, 4)
        q_start = jnp.asarray(self._q_start, jnp.float32)

        def one(v: jax.Array) -> jax.Array:
            def solve(q: jax.Array, p: jax.Array) -> tuple[jax.Array, jax.Array]:
                target = jnp.array([p[0], p[1], self.height])
                q, _ = self._kinematics.inverse(q, target, p[2])
                return q, q

            _, q_via = jax.lax.scan(solve, q_start, v)
            return kuka.joint_trajectory(q_start, q_via, v[:, 3], self.horizon)

        return jax.vmap(one)(via)

    def evaluate(self, actions: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        return self.evaluate_masked(actions, key, jnp.ones(actions.shape[0], bool))

    def evaluate_masked(self, actions: jax.Array, key: jax.Array,
                        mask: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        ctrl = self.controls(actions)
        if self.physics == "mjx":
            qpos, path, finite = self._rollout(ctrl, mask)
        else:
            batch, nq = actions.shape[0], kuka.load(self.scene).nq
            shapes = (jax.ShapeDtypeStruct((batch, nq), jnp.float32), jax.ShapeDtypeStruct((batch,), jnp.float32),
                      jax.ShapeDtypeStruct((batch,), jnp.bool_))
            qpos, path, finite = jax.pure_callback(self._rollout, shapes, ctrl, mask, vmap_method="expand_dims")
        obj = qpos[:, 7:10]
        low, high = jnp.asarray(kuka.TABLE_LOW), jnp.asarray(kuka.TABLE_HIGH)
        on_table = (obj[:, :2] >= low).all(1) & (obj[:, :2] <= high).all(1) & (obj[:, 2] > 0.5 * self.height)
        return obj[:, :2], -path, finite & on_table


def make(scene: str, height: float, backend: str = "auto", t_max: float = T_MAX, settle: int = SETTLE) -> Push:
    """A push task; `t_max` and `settle` shorten the horizon for quick checks."""
    (x0, y0), (x1, y1) = kuka.REACH_LOW, kuka.REACH_HIGH
    h = math.pi / 2
    low = (x0, y0, -h, min(T_MIN, t_max)) * VIA_POINTS
    high = (x1, y1, h, t_max) * VIA_POINTS
    return Push(low, high, kuka.TABLE_LOW, kuka.TABLE_HIGH, scene=scene, height=height, backend=backend,
                horizon=VIA_POINTS * math.ceil(t_max) + settle)
