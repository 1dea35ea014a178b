"""The physics backends: one MjModel behind one interface,
`rollout(ctrl [..., H, nu], mask [...]) -> (final qpos, sensor readings at every step, finite)`,
from a start state (an MjData):

* `CRollout` ("mujoco", for CPUs): C MuJoCo through `mujoco.rollout` (one MjData
  per CPU thread), called from inside the jitted generation with
  `jax.pure_callback` on the whole batch at once (`vmap_method="expand_dims"`: a
  vmap over seeds also becomes one call; `simulate`). Rows outside the mask are not simulated.
* `MjxRollout` ("mjx", for accelerators; "warp": MuJoCo Warp through MJX): `mjx.step`
  in a `lax.scan`, vmapped over the batch; fully traced, so masked rows are simulated and ignored.

`resolve(backend, model)` turns a task's `backend` option ("auto", "mujoco", "mjx",
"warp") into the backend it runs on, refusing what cannot run, and `make` builds it.
"""

from __future__ import annotations

import contextlib
import importlib.util
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

BACKENDS = ("auto", "mujoco", "mjx", "warp")


def warp_installed() -> bool:
    """Whether MuJoCo Warp (and Warp) can be imported."""
    return importlib.util.find_spec("mujoco_warp") is not None and importlib.util.find_spec("warp") is not None


def auto_backend() -> str:
    """"mujoco" on a CPU, "warp" on a CUDA GPU when MuJoCo Warp is installed, else "mjx"."""
    if jax.default_backend() == "cpu":
        return "mujoco"
    return "warp" if jax.default_backend() == "gpu" and warp_installed() else "mjx"


def resolve(backend: str, model: mujoco.MjModel) -> str:
    """The backend a task with option `backend` runs on ("mujoco", "mjx" or "warp"); ValueError for an unknown
    option, "warp" without MuJoCo Warp, or "mjx" for a model that needs MuJoCo's discrete integrator."""
    if backend not in BACKENDS:
        raise ValueError(f"backend={backend!r} is invalid: expected one of {BACKENDS}")
    backend = auto_backend() if backend == "auto" else backend
    if backend == "warp" and not warp_installed():
        raise ValueError("backend='warp' needs MuJoCo Warp: pip install -e .[gpu]")
    if backend == "mjx" and model.opt.integrator == mujoco.mjtIntegrator.mjINT_DISCRETE:
        raise ValueError("this scene needs MuJoCo's discrete integrator (a friction grasp), which MJX's JAX "
                         "implementation does not have: use backend='mujoco' (CPUs) or 'warp' (NVIDIA GPUs; "
                         "pip install -e .[gpu])")
    return backend


def make(backend: str, model: mujoco.MjModel, data: mujoco.MjData) -> CRollout | MjxRollout:
    """The rollouts of `resolve`d `backend` from the start state `data`."""
    return CRollout(model, data) if backend == "mujoco" else MjxRollout(model, data, backend if backend == "warp"
                                                                          else "jax")


def simulate(rollouts: CRollout | MjxRollout, model: mujoco.MjModel, ctrl: jax.Array,
             mask: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """ctrl [B, H, nu], mask [B] -> final qpos [B, nq], sensors [B, H, ns], finite [B] of `model`, traced: MJX in the
    program (running every row), anything else (C MuJoCo) through `jax.pure_callback` (skipping the rows outside
    the mask)."""
    if isinstance(rollouts, MjxRollout):
        return rollouts(ctrl, mask)
    batch, horizon = ctrl.shape[0], ctrl.shape[1]
    shapes = (jax.ShapeDtypeStruct((batch, model.nq), jnp.float32),
              jax.ShapeDtypeStruct((batch, horizon, model.nsensordata), jnp.float32),
              jax.ShapeDtypeStruct((batch,), jnp.bool_))
    return jax.pure_callback(rollouts, shapes, ctrl, mask, vmap_method="expand_dims")


def frames(rollouts: CRollout, ctrl: np.ndarray, width: int, height: int, every: int, camera: mujoco.MjvCamera,
           follow: bool = False) -> np.ndarray:
    """Frames [F, height, width, 3] uint8 of one C MuJoCo rollout of ctrl [1, H, nu], a frame every `every` steps,
    seen by `camera` (looking at the first body's position at each frame with `follow`). Needs an OpenGL context
    (MUJOCO_GL=egl offscreen)."""
    model = rollouts.model
    state, _ = rollout.rollout(model, rollouts.datas[:1], rollouts.initial_state[None], ctrl)
    data = mujoco.MjData(model)
    out = []
    with mujoco.Renderer(model, height, width) as renderer:
        for t in range(0, state.shape[1], every):
            mujoco.mj_setState(model, data, state[0, t], mujoco.mjtState.mjSTATE_FULLPHYSICS)
            mujoco.mj_forward(model, data)
            if follow:
                camera.lookat[:] = data.qpos[:3]
            renderer.update_scene(data, camera)
            out.append(renderer.render())
    return np.stack(out)


class CRollout:
    """C MuJoCo rollouts of a batch of control sequences (the actuators' targets) from a start state `data` of
    `model`."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        self.model = model
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


# MuJoCo Warp's buffers: contacts per world (a cube on a table touches at up to 8 points; pads and shelves
# add some) and constraint rows per world (contacts with friction, joint limits, the pads' coupling).
WARP_CONTACTS_PER_WORLD = 64
WARP_CONSTRAINTS_PER_WORLD = 512


class MjxRollout:
    """MJX rollouts of a batch of control sequences from a start state `data` of `model` (traced; same controls).

    `impl`: "jax" (MJX's JAX implementation: any JAX device) or "warp" (MuJoCo
    Warp through MJX: NVIDIA GPUs, and Warp's CPU device; needs the `gpu` extra).
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, impl: str = "jax") -> None:
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
