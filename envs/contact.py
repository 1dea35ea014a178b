"""Where a pusher's commanded path meets a round object: features M-QD's model takes (`Task.features`).

Whether a push moves an object at all depends on whether the pusher's path
meets it, which a network of the raw action learns poorly (a thin set of
actions touches, the rest leave the object where it was). The path itself
follows from the action without physics (a point robot's velocities, an arm's
forward kinematics), so a task can hand the model what it implies:

    touched      +1 if the path comes within `reach` of the object's centre, else -1
    closest      the path's closest approach to the centre, in units of `reach`, mapped from [0, 4] to [-1, 1]
    touch point  (x, y) where the path first comes within `reach` (the path's end if never), in box units [-1, 1]
    direction    the path's unit direction of motion there (0, 0 if it never touches)
    past         how far the path goes on after that point, in units of the box's half-diagonal, from [0, 2] to [-1, 1]
    end          (x, y) where the path ends, in box units [-1, 1]

Nine numbers, no dynamics: the object's own motion (sliding, rolling, tipping)
is left to the model. `swept` adds a tenth and eleventh: where the object would
end if the pusher swept it along without friction or inertia (a disk kept just
out of the pusher's reach), a geometric guess the model corrects. (On 2D
Object, whose dynamics are that sweep, it would be the outcome itself, so that
task does not give it.)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def box_units(points: jax.Array, low: tuple[float, ...], high: tuple[float, ...]) -> jax.Array:
    """points [..., 2] mapped from the box `low`..`high` (its first two axes) to [-1, 1]: the units of every
    position among the tasks' features and auxiliary outputs."""
    low_, high_ = jnp.asarray(low, jnp.float32)[:2], jnp.asarray(high, jnp.float32)[:2]
    return 2.0 * (points - low_) / (high_ - low_) - 1.0


def path_contact(path: jax.Array, near: jax.Array, centre: tuple[float, float], reach: float,
                 low: tuple[float, ...], high: tuple[float, ...]) -> jax.Array:
    """Features [B, 9] (see the module's doc) of paths [B, T, 2] against a disk at `centre` of radius `reach`.

    `near` [B, T] bool: where a path point can touch at all (an arm's tool low enough); the others
    count as far. `low`, `high`: the box that positions are scaled by (the behavior box).
    """
    to_box = lambda p: box_units(p, low, high)  # noqa: E731
    half_diagonal = 0.5 * jnp.linalg.norm(jnp.asarray(high, jnp.float32)[:2] - jnp.asarray(low, jnp.float32)[:2])
    dist = jnp.where(near, jnp.linalg.norm(path - jnp.asarray(centre, jnp.float32), axis=-1), jnp.inf)  # [B, T]
    touching = dist < reach
    touched = touching.any(axis=1)
    first = jnp.where(touched, jnp.argmax(touching, axis=1), path.shape[1] - 1)  # [B]
    point = jnp.take_along_axis(path, first[:, None, None], axis=1)[:, 0]
    steps = jnp.diff(path, axis=1)  # [B, T - 1, 2]
    lengths = jnp.linalg.norm(steps, axis=-1)
    after = jnp.arange(path.shape[1] - 1) >= first[:, None]
    # The direction of motion at the touch: the first step after it that moves.
    moving = after & (lengths > 1e-6)
    step = jnp.take_along_axis(steps, jnp.argmax(moving, axis=1)[:, None, None], axis=1)[:, 0]
    direction = jnp.where((touched & moving.any(axis=1))[:, None],
                          step / jnp.maximum(jnp.linalg.norm(step, axis=-1, keepdims=True), 1e-6), 0.0)
    past = jnp.where(touched, jnp.where(after, lengths, 0.0).sum(axis=1), 0.0)
    closest = jnp.clip(jnp.where(jnp.isfinite(dist), dist, 4.0 * reach).min(axis=1) / reach, 0.0, 4.0)
    return jnp.concatenate([jnp.where(touched, 1.0, -1.0)[:, None], (closest / 2.0 - 1.0)[:, None], to_box(point),
                            direction, jnp.clip(past / half_diagonal, 0.0, 2.0)[:, None] - 1.0, to_box(path[:, -1])],
                           axis=1).astype(jnp.float32)


def swept(path: jax.Array, near: jax.Array, centre: tuple[float, float], reach: float, low: tuple[float, ...],
          high: tuple[float, ...]) -> jax.Array:
    """[B, 2] where a disk at `centre` ends, in box units [-1, 1], if each point of paths [B, T, 2] that can touch
    (`near` [B, T]) pushes it straight out of its reach: the disk's centre is moved along the line from the point
    to `reach` from it. Geometry only (no friction, no inertia, no rotation)."""

    def step(disk: jax.Array, point: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, None]:
        at, can = point
        away = disk - at
        dist = jnp.linalg.norm(away, axis=-1, keepdims=True)
        pushed = at + reach * away / jnp.maximum(dist, 1e-9)
        return jnp.where(can[:, None] & (dist < reach), pushed, disk), None

    start = jnp.broadcast_to(jnp.asarray(centre, jnp.float32), (path.shape[0], 2))
    end, _ = jax.lax.scan(step, start, (jnp.moveaxis(path, 1, 0), near.T))
    return box_units(end, low, high)
