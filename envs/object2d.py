"""2D Object: push a round object with a round agent (5 sub-actions).

The agent (radius `AGENT_RADIUS`) moves as in `arena2d`, its centre kept
inside the arena. When it overlaps the object (radius `OBJECT_RADIUS`) it pushes
it quasi-statically: the object is moved along the line of centres until the two
just touch, then kept inside the arena; if the wall stopped it, the agent is put
back in contact. Behavior: the object's final position. Quality: `delta_min /
delta` with `delta` the object's path length and `delta_min` the straight line
from its start (1 if it never moved).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from envs import arena2d
from mqd_jax.task import Task

AGENT_START = (0.5, 0.2)
OBJECT_START = (0.5, 0.5)
AGENT_RADIUS = 0.02
OBJECT_RADIUS = 0.05


def _separate(mover: jax.Array, fixed: jax.Array, gap: float) -> jax.Array:
    """Moves `mover` away from `fixed` along their line of centres to distance >= gap."""
    diff = mover - fixed
    dist = jnp.linalg.norm(diff)
    direction = jnp.where(dist > 1e-9, diff / jnp.maximum(dist, 1e-9), jnp.array([0.0, 1.0]))
    return jnp.where(dist < gap, fixed + direction * gap, mover)


@dataclasses.dataclass(frozen=True, eq=False)
class Object2D(Task):
    agent_start: tuple[float, float] = AGENT_START
    object_start: tuple[float, float] = OBJECT_START

    def _rollout(self, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        gap = AGENT_RADIUS + OBJECT_RADIUS
        no_boxes = jnp.zeros((0, 4), jnp.float32)

        def step(carry: tuple[jax.Array, jax.Array, jax.Array], delta: jax.Array):
            agent, obj, travelled = carry
            agent = arena2d.move(agent, delta, no_boxes, AGENT_RADIUS, 1 - AGENT_RADIUS)
            new_obj = jnp.clip(_separate(obj, agent, gap), OBJECT_RADIUS, 1 - OBJECT_RADIUS)
            agent = jnp.clip(_separate(agent, new_obj, gap), AGENT_RADIUS, 1 - AGENT_RADIUS)
            return agent, new_obj, travelled + jnp.linalg.norm(new_obj - obj)

        init = (jnp.asarray(self.agent_start, jnp.float32), jnp.asarray(self.object_start, jnp.float32),
                jnp.float32(0.0))
        _, obj, travelled = arena2d.rollout(action, init, step)
        return obj, travelled

    def evaluate(self, actions: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        final, travelled = jax.vmap(self._rollout)(actions)
        shortest = jnp.linalg.norm(final - jnp.asarray(self.object_start), axis=-1)
        return final, arena2d.path_quality(shortest, travelled), jnp.ones(actions.shape[0], bool)

    def reachable(self, points: np.ndarray) -> np.ndarray:
        """Object centres stay OBJECT_RADIUS away from the walls."""
        lo, hi = OBJECT_RADIUS, 1 - OBJECT_RADIUS
        return np.all((points >= lo) & (points <= hi), axis=-1)


def make() -> Object2D:
    low, high = arena2d.action_bounds(5)
    return Object2D(low, high, (0.0, 0.0), (1.0, 1.0))
