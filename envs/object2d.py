"""2D Object: push a round object with a round agent (5 sub-actions).

The agent (radius `agent_radius`) moves as in `arena2d`, its centre kept
inside the arena. When it overlaps the object (radius `object_radius`) it pushes
it quasi-statically: the object is moved along the line of centres until the two
just touch, then kept inside the arena; if the wall stopped it, the agent is put
back in contact. Behavior: the object's final position. Quality: `delta_min /
delta` with `delta` the object's path length and `delta_min` the straight line
from its start (1 if it never moved).

Auxiliary output (`Task.auxiliary`, for M-QD's gate): "moved", +1 where the
agent moved the object, else -1. No features (`Task.features`): where the
agent's path meets the object (`envs.contact.path_contact`) cost M-QD coverage
here in measurement (docs/results.md, "Version 0.11"), and where it would sweep
the object is this task's own dynamics, the outcome itself.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import numpy as np

from envs import arena2d
from mqd_jax.core.task import Region, Task

# The agent starts in a corner, 0.57 from the object at the centre: a random path of 5 sub-actions seldom
# reaches it, and a repertoire has to learn to get there before it can learn where to push it
# (docs/results.md: RANDOM covers about a third of what QD covers, as in the paper).
AGENT_START = (0.1, 0.1)
OBJECT_START = (0.5, 0.5)
AGENT_RADIUS = 0.04
OBJECT_RADIUS = 0.05


def _separate(mover: arena2d.Array, fixed: arena2d.Array, gap: float) -> arena2d.Array:
    """Moves mover[B, 2] away from fixed[B, 2] along their line of centres to distance >= gap."""
    xp = arena2d.xp_of(mover, fixed)
    diff = mover - fixed
    dist = xp.linalg.norm(diff, axis=1, keepdims=True)
    direction = xp.where(dist > 1e-9, diff / xp.maximum(dist, 1e-9), xp.asarray([0.0, 1.0], np.float32))
    return xp.where(dist < gap, fixed + direction * gap, mover)


@dataclasses.dataclass(frozen=True, eq=False)
class Object2D(Task):
    paper_coverage: ClassVar[dict[str, tuple[float, float]]] = {
        "mqd": (0.504, 0.073), "qd": (0.366, 0.064), "random": (0.035, 0.002)}

    agent_start: tuple[float, float] = AGENT_START
    object_start: tuple[float, float] = OBJECT_START
    agent_radius: float = AGENT_RADIUS
    object_radius: float = OBJECT_RADIUS

    auxiliary = ("moved",)

    def evaluate(self, actions: arena2d.Array, key: jax.Array | None = None):
        """Rolls out actions[B, 15]; numpy in, numpy out (JAX in, JAX out). `key` is unused."""
        return self.evaluate_with_auxiliary(actions, key)[:3]

    def evaluate_with_auxiliary(self, actions: arena2d.Array, key: jax.Array | None = None,
                                mask: jax.Array | None = None):
        """`evaluate`'s outputs and "moved" [B, 1]: +1 where the agent moved the object, else -1."""
        xp = arena2d.xp_of(actions)
        ra, ro = self.agent_radius, self.object_radius
        gap = ra + ro
        no_boxes = xp.zeros((0, 4), np.float32)

        def step(carry, delta):
            agent, obj, travelled = carry
            agent = arena2d.move(agent, delta, no_boxes, ra, 1 - ra)
            new_obj = xp.clip(_separate(obj, agent, gap), ro, 1 - ro)
            agent = xp.clip(_separate(agent, new_obj, gap), ra, 1 - ra)
            return agent, new_obj, travelled + xp.linalg.norm(new_obj - obj, axis=1)

        batch = actions.shape[0]
        start = lambda p: xp.broadcast_to(xp.asarray(p, np.float32), (batch, 2))  # noqa: E731
        init = (start(self.agent_start), start(self.object_start), xp.zeros(batch, np.float32))
        _, final, travelled = arena2d.rollout(actions, init, step)
        shortest = xp.linalg.norm(final - xp.asarray(self.object_start, np.float32), axis=1)
        moved = xp.where(travelled > 0, 1.0, -1.0).astype(np.float32)[:, None]
        return final, arena2d.path_quality(shortest, travelled), xp.ones(batch, bool), moved

    def reachable(self, points: np.ndarray) -> np.ndarray:
        """Object centres stay object_radius away from the walls."""
        lo, hi = self.object_radius, 1 - self.object_radius
        return np.all((points >= lo) & (points <= hi), axis=-1)

    def frames(self, action: np.ndarray, width: int = 320, height: int = 320) -> np.ndarray:
        """The behavior along the skill `action`, drawn over the layout (40 frames)."""
        return arena2d.frames(self, action, width, height)

    def layout(self) -> tuple[Region, ...]:
        disk = lambda label, c, r, colour: Region(label, (c[0] - r, c[1] - r), (c[0] + r, c[1] + r),  # noqa: E731
                                                  "disk", colour=colour)
        return (disk("object start", self.object_start, self.object_radius, "tab:red"),
                disk("agent start", self.agent_start, self.agent_radius, "tab:green"))


def make() -> Object2D:
    low, high = arena2d.action_bounds(5)
    return Object2D(low, high, (0.0, 0.0), (1.0, 1.0))
