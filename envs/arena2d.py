"""The paper's 2D environment: a point agent in the unit square.

An action is a sequence of sub-actions `(x_dot, y_dot, T)`, executed one after
another: velocity `(x_dot, y_dot)` in [-1, 1]^2 (arena units per time unit) is
applied for `T` in [0, `max_duration`] time steps of length `DT`. `T` is
continuous: the last, partial step moves the agent by the fraction of a step
that remains, so a behavior is a continuous function of the action.

Walls and obstacles are axis-aligned boxes. The agent slides along them: each
time step moves along x and then along y, and each move stops at the first face
it would cross, so motion tangent to a face continues.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

DT = 0.05
MAX_DURATION = 10.0
SUB_ACTION_LOW = (-1.0, -1.0, 0.0)
SUB_ACTION_HIGH = (1.0, 1.0, MAX_DURATION)

Boxes = jax.Array  # [m, 4] rows (x_lo, y_lo, x_hi, y_hi)


def action_bounds(num_sub_actions: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Bounds of an action made of `num_sub_actions` sub-actions (x_dot, y_dot, T)."""
    return SUB_ACTION_LOW * num_sub_actions, SUB_ACTION_HIGH * num_sub_actions


def step_displacements(action: jax.Array) -> jax.Array:
    """Per-time-step displacement requested by `action[3 s]`; shape [s * 10, 2]."""
    sub = action.reshape(-1, 3)
    steps = jnp.arange(int(MAX_DURATION), dtype=action.dtype)
    frac = jnp.clip(sub[:, 2:3] - steps[None, :], 0.0, 1.0)  # [s, 10]
    disp = sub[:, None, :2] * DT * frac[:, :, None]  # [s, 10, 2]
    return disp.reshape(-1, 2)


def _move_axis(pos: jax.Array, delta: jax.Array, axis: int, boxes: Boxes, lo: float, hi: float) -> jax.Array:
    """Moves coordinate `axis` of `pos` by `delta`, stopping at box faces and walls."""
    other = 1 - axis
    x, y = pos[axis], pos[other]
    target = x + delta
    b_lo, b_hi = boxes[:, axis], boxes[:, axis + 2]
    spans = (boxes[:, other] < y) & (y < boxes[:, other + 2])
    stop_up = jnp.where(spans & (x <= b_lo) & (target > b_lo), b_lo, jnp.inf).min(initial=jnp.inf)
    stop_down = jnp.where(spans & (x >= b_hi) & (target < b_hi), b_hi, -jnp.inf).max(initial=-jnp.inf)
    target = jnp.clip(target, stop_down, stop_up)
    return pos.at[axis].set(jnp.clip(target, lo, hi))


def move(pos: jax.Array, delta: jax.Array, boxes: Boxes, lo: float = 0.0, hi: float = 1.0) -> jax.Array:
    """One time step of sliding motion of a point inside [lo, hi]^2 among `boxes`."""
    pos = _move_axis(pos, delta[0], 0, boxes, lo, hi)
    return _move_axis(pos, delta[1], 1, boxes, lo, hi)


def rollout(action: jax.Array, init: jax.Array, step: Callable[[jax.Array, jax.Array], jax.Array]) -> jax.Array:
    """Scans `step(carry, displacement) -> carry` over the action's time steps."""
    carry, _ = jax.lax.scan(lambda c, d: (step(c, d), None), init, step_displacements(action))
    return carry


def path_quality(shortest: jax.Array, travelled: jax.Array) -> jax.Array:
    """`delta_min / delta` in [0, 1]; 1 for a rollout that never moved."""
    moved = travelled > 1e-9
    return jnp.where(moved, jnp.clip(shortest / jnp.where(moved, travelled, 1.0), 0.0, 1.0), 1.0)
