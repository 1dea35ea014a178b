"""The paper's 2D environment: a point agent in the unit square.

An action is a sequence of sub-actions `(x_dot, y_dot, T)`, executed one after
another: velocity `(x_dot, y_dot)` in [-1, 1]^2 (arena units per time unit) is
applied for `T` in [0, `MAX_DURATION`] time steps of length `DT`. `T` is
continuous: the last, partial step moves the agent by the fraction of a step
that remains, so a behavior is a continuous function of the action.

Walls and obstacles are axis-aligned boxes. The agent slides along them: each
time step moves along x and then along y, and each move stops at the first face
it would cross, so motion tangent to a face continues. An obstacle that touches
an arena wall is sealed to it (`sealed`): its faces on the wall are moved beyond
it, so an agent sliding along the wall cannot pass through the obstacle's end.

Every function here works on batches of numpy arrays as well as JAX arrays, so
peers that need plain numpy (the pyribs benchmark, an ask/tell evaluator) run
exactly the same dynamics.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

DT = 0.05
MAX_DURATION = 10.0
SUB_ACTION_LOW = (-1.0, -1.0, 0.0)
SUB_ACTION_HIGH = (1.0, 1.0, MAX_DURATION)

Array = Any  # numpy or JAX array


def xp_of(*arrays: Array) -> Any:
    """numpy for numpy inputs, jax.numpy as soon as one input is a JAX array."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


def action_bounds(num_sub_actions: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Bounds of an action made of `num_sub_actions` sub-actions (x_dot, y_dot, T)."""
    return SUB_ACTION_LOW * num_sub_actions, SUB_ACTION_HIGH * num_sub_actions


def step_displacements(actions: Array) -> Array:
    """Per-time-step displacements requested by actions[B, 3 s]; shape [s * 10, B, 2]."""
    xp = xp_of(actions)
    sub = actions.reshape(actions.shape[0], -1, 3)  # [B, s, 3]
    steps = xp.arange(int(MAX_DURATION), dtype=actions.dtype)
    frac = xp.clip(sub[:, :, 2:3] - steps, 0.0, 1.0)  # [B, s, 10]
    disp = sub[:, :, None, :2] * DT * frac[..., None]  # [B, s, 10, 2]
    return xp.moveaxis(disp.reshape(actions.shape[0], -1, 2), 1, 0)


def sealed(boxes: np.ndarray, lo: float = 0.0, hi: float = 1.0) -> np.ndarray:
    """boxes [m, 4] (x_lo, y_lo, x_hi, y_hi) with every face that lies on or beyond an arena wall moved one
    arena width past it: a box that touches a wall then spans an agent sliding along that wall (the motion and
    visibility tests are strict, so they would let it pass along a face that ends exactly at the wall)."""
    boxes = np.array(boxes, np.float32)
    width = hi - lo
    boxes[:, :2] = np.where(boxes[:, :2] <= lo, lo - width, boxes[:, :2])
    boxes[:, 2:] = np.where(boxes[:, 2:] >= hi, hi + width, boxes[:, 2:])
    return boxes


def _move_axis(pos: Array, delta: Array, axis: int, boxes: Array, lo: float, hi: float) -> Array:
    """Moves coordinate `axis` of pos[B, 2] by delta[B], stopping at box faces and walls."""
    xp = xp_of(pos, delta)
    other = 1 - axis
    x, y = pos[:, axis, None], pos[:, other, None]
    target = x[:, 0] + delta
    b_lo, b_hi = boxes[:, axis], boxes[:, axis + 2]
    spans = (boxes[:, other] < y) & (y < boxes[:, other + 2])
    up = spans & (x <= b_lo) & (target[:, None] > b_lo)
    down = spans & (x >= b_hi) & (target[:, None] < b_hi)
    stop_up = xp.where(up, b_lo, xp.inf).min(axis=1, initial=xp.inf)
    stop_down = xp.where(down, b_hi, -xp.inf).max(axis=1, initial=-xp.inf)
    new = xp.clip(xp.clip(target, stop_down, stop_up), lo, hi)
    return xp.stack([new, pos[:, other]] if axis == 0 else [pos[:, other], new], axis=1)


def move(pos: Array, delta: Array, boxes: Array, lo: float = 0.0, hi: float = 1.0) -> Array:
    """One time step of sliding motion of points pos[B, 2] inside [lo, hi]^2 among boxes[m, 4]."""
    pos = _move_axis(pos, delta[:, 0], 0, boxes, lo, hi)
    return _move_axis(pos, delta[:, 1], 1, boxes, lo, hi)


def rollout(actions: Array, init: Any, step: Callable[[Any, Array], Any]) -> Any:
    """Folds `step(carry, displacements[B, 2]) -> carry` over the time steps of actions[B, n].

    A `lax.scan` for JAX inputs, a Python loop over time steps for numpy.
    """
    disp = step_displacements(actions)
    if xp_of(actions) is jnp:
        return jax.lax.scan(lambda c, d: (step(c, d), None), init, disp)[0]
    for d in disp:
        init = step(init, d)
    return init


def free_path(actions: jax.Array, start: tuple[float, float], lo: float = 0.0, hi: float = 1.0) -> jax.Array:
    """The positions [B, T + 1, 2] (start first) of a point that follows actions [B, n] through an arena without
    obstacles, kept inside [lo, hi]^2: what a task can know of the path without its obstacles (`Task.features`)."""
    start_ = jnp.broadcast_to(jnp.asarray(start, jnp.float32), (actions.shape[0], 2))

    def step(pos: jax.Array, delta: jax.Array) -> tuple[jax.Array, jax.Array]:
        pos = jnp.clip(pos + delta, lo, hi)
        return pos, pos

    _, path = jax.lax.scan(step, start_, step_displacements(actions))
    return jnp.concatenate([start_[:, None], jnp.moveaxis(path, 0, 1)], axis=1)


def path_quality(shortest: Array, travelled: Array) -> Array:
    """`delta_min / delta` in [0, 1]; 1 for a rollout that never moved."""
    xp = xp_of(shortest, travelled)
    moved = travelled > 1e-9
    return xp.where(moved, xp.clip(shortest / xp.where(moved, travelled, 1.0), 0.0, 1.0), 1.0)


def truncated(action: np.ndarray, times: np.ndarray) -> np.ndarray:
    """action [3 s] stopped after each of times [F] (time steps from the start): [F, 3 s].

    Sub-action i occupies the time steps [i * MAX_DURATION, (i + 1) * MAX_DURATION)
    (see `step_displacements`), so cutting its duration to the part of that
    window before a time gives the position at that time.
    """
    sub = np.asarray(action, np.float32).reshape(-1, 3)
    window = np.arange(len(sub), dtype=np.float32) * MAX_DURATION
    out = np.broadcast_to(sub, (len(times), *sub.shape)).copy()
    out[..., 2] = np.clip(np.asarray(times, np.float32)[:, None] - window, 0.0, sub[:, 2])
    return out.reshape(len(times), -1)


def frames(task: Any, action: np.ndarray, width: int, height: int, num: int = 40) -> np.ndarray:
    """`Task.frames` of a 2D task: its behavior along the action, `num` frames, drawn over its layout."""
    from mqd_jax.experiment import plots

    end = len(np.asarray(action)) // 3 * MAX_DURATION
    path, _, _ = task.evaluate(truncated(action, np.linspace(0.0, end, num)))
    return plots.path_frames(task, np.asarray(path), width, height, type(task).__name__)
