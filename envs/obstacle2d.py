"""2D Obstacle: navigate a point agent around obstacles (3 sub-actions).

Behavior: the agent's final position. Quality: `delta_min / delta`, where
`delta` is the length of the path the agent travelled and `delta_min` the length
of the shortest obstacle-free path from the start to the final position. Among
axis-aligned boxes that shortest path bends only at box corners, so it is exact:
a visibility graph over the start and the corners, solved once on the host.
Obstacles that touch the arena's walls are sealed to them (`arena2d.sealed`) for
both the motion and the shortest path.

Features (`Task.features`, for M-QD's model): the path the action would take
without obstacles (`arena2d.free_path`): its end, whether and where it first
crosses an obstacle, and how far it would go on past that point.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from envs import arena2d
from mqd_jax.core.task import Region, Task

START = (0.5, 0.1)
AGENT_MARK = 0.015  # radius of the start marker in figures (the agent is a point)
# (x_lo, y_lo, x_hi, y_hi): a wall with a gap, a block behind the gap and a
# block right above the start.
OBSTACLES = (
    (0.0, 0.5, 0.35, 0.55),
    (0.65, 0.5, 1.0, 0.55),
    (0.35, 0.75, 0.65, 0.8),
    (0.4, 0.2, 0.6, 0.25),
)


def segment_blocked(p: jax.Array, q: jax.Array, boxes: jax.Array) -> jax.Array:
    """Whether segment p->q passes through the open interior of any box.

    Slab test with strict inequalities, so a segment along a face or through a
    corner is not blocked. Works on numpy and JAX arrays (p, q: [..., 2]).
    """
    xp = arena2d.xp_of(p, q)
    d = q - p
    t_lo = xp.zeros((*p.shape[:-1], boxes.shape[0]))
    t_hi = xp.ones_like(t_lo)
    inside = xp.ones_like(t_lo, dtype=bool)
    for ax in range(2):
        lo, hi = boxes[:, ax], boxes[:, ax + 2]
        pa, da = p[..., ax][..., None], d[..., ax][..., None]
        still = da == 0
        safe = xp.where(still, 1.0, da)
        t1, t2 = (lo - pa) / safe, (hi - pa) / safe
        t_lo = xp.where(still, t_lo, xp.maximum(t_lo, xp.minimum(t1, t2)))
        t_hi = xp.where(still, t_hi, xp.minimum(t_hi, xp.maximum(t1, t2)))
        inside = inside & xp.where(still, (lo < pa) & (pa < hi), True)
    return xp.any(inside & (t_lo < t_hi), axis=-1)


def _length(steps: jax.Array) -> jax.Array:
    """The steps' lengths [B, T] from steps [B, T, 2], with a zero gradient (not NaN) at a zero step."""
    squared = (steps * steps).sum(axis=-1)
    moved = squared > 0
    return jnp.where(moved, jnp.sqrt(jnp.where(moved, squared, 1.0)), 0.0)


def _graph(start: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (start + box corners inside the arena) and their geodesic distance from start."""
    corners = np.concatenate([boxes[:, [0, 1]], boxes[:, [2, 1]], boxes[:, [0, 3]], boxes[:, [2, 3]]])
    corners = corners[np.all((corners >= 0) & (corners <= 1), axis=1)]
    nodes = np.concatenate([start[None], corners]).astype(np.float64)
    n = len(nodes)
    p, q = np.repeat(nodes, n, 0), np.tile(nodes, (n, 1))
    blocked = segment_blocked(p, q, boxes).reshape(n, n)
    dist = np.where(blocked, np.inf, np.linalg.norm(nodes[:, None] - nodes[None], axis=-1))
    for m in range(n):  # Floyd-Warshall: a handful of nodes.
        dist = np.minimum(dist, dist[:, m:m + 1] + dist[m:m + 1, :])
    return nodes.astype(np.float32), dist[0].astype(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class Obstacle2D(Task):
    paper_coverage: ClassVar[dict[str, tuple[float, float]]] = {
        "mqd": (0.971, 0.018), "qd": (0.875, 0.017), "random": (0.731, 0.004)}

    start: tuple[float, float] = START
    obstacles: tuple[tuple[float, float, float, float], ...] = OBSTACLES

    def __post_init__(self) -> None:
        blocking = arena2d.sealed(np.asarray(self.obstacles))
        nodes, dist = _graph(np.asarray(self.start), blocking.astype(np.float64))
        object.__setattr__(self, "_blocking", blocking)
        object.__setattr__(self, "_nodes", nodes)
        object.__setattr__(self, "_node_dist", dist)

    def shortest_path(self, points: arena2d.Array) -> arena2d.Array:
        """Geodesic distance from the start to each free point points[B, 2]."""
        xp = arena2d.xp_of(points)
        nodes = xp.asarray(self._nodes)
        p = xp.broadcast_to(points[:, None, :], (points.shape[0], *nodes.shape))
        seen = ~segment_blocked(xp.broadcast_to(nodes, p.shape), p, xp.asarray(self._blocking))
        via = xp.asarray(self._node_dist) + xp.linalg.norm(p - nodes, axis=-1)
        return xp.where(seen, via, xp.inf).min(axis=-1)

    def evaluate(self, actions: arena2d.Array, key: jax.Array | None = None):
        """Rolls out actions[B, 9]; numpy in, numpy out (JAX in, JAX out). `key` is unused."""
        xp = arena2d.xp_of(actions)
        boxes = xp.asarray(self._blocking)

        def step(carry, delta):
            pos, travelled = carry
            new = arena2d.move(pos, delta, boxes)
            return new, travelled + xp.linalg.norm(new - pos, axis=1)

        batch = actions.shape[0]
        init = (xp.broadcast_to(xp.asarray(self.start, np.float32), (batch, 2)), xp.zeros(batch, np.float32))
        final, travelled = arena2d.rollout(actions, init, step)
        quality = arena2d.path_quality(self.shortest_path(final), travelled)
        return final, quality, xp.ones(batch, bool)

    def features(self, actions: jax.Array) -> jax.Array:
        """[B, 6]: the free path's end (x, y), +1 if it crosses an obstacle (else -1), the point (x, y) before
        its first crossing (the end if none) and the length it goes on past it (clipped to [0, 2]); positions
        mapped from the arena to [-1, 1]."""
        path = arena2d.free_path(actions, self.start)
        steps = jnp.diff(path, axis=1)
        crosses = segment_blocked(path[:, :-1], path[:, 1:], jnp.asarray(self._blocking))  # [B, T]
        crossed = crosses.any(axis=1)
        first = jnp.where(crossed, jnp.argmax(crosses, axis=1), steps.shape[1])
        hit = jnp.take_along_axis(path, first[:, None, None], axis=1)[:, 0]
        past = jnp.where(jnp.arange(steps.shape[1]) >= first[:, None], _length(steps), 0.0).sum(1)
        return jnp.concatenate([2.0 * path[:, -1] - 1.0, jnp.where(crossed, 1.0, -1.0)[:, None], 2.0 * hit - 1.0,
                                jnp.clip(past, 0.0, 2.0)[:, None] - 1.0], axis=1)

    def reachable(self, points: np.ndarray) -> np.ndarray:
        """Free space: outside every obstacle (all of it is connected to the start)."""
        boxes = np.asarray(self.obstacles)
        x, y = points[..., 0, None], points[..., 1, None]
        inside = (boxes[:, 0] < x) & (x < boxes[:, 2]) & (boxes[:, 1] < y) & (y < boxes[:, 3])
        return ~inside.any(-1)

    def frames(self, action: np.ndarray, width: int = 320, height: int = 320) -> np.ndarray:
        """The behavior along the skill `action`, drawn over the layout (40 frames)."""
        return arena2d.frames(self, action, width, height)

    def layout(self) -> tuple[Region, ...]:
        r = AGENT_MARK
        start = Region("agent start", (self.start[0] - r, self.start[1] - r), (self.start[0] + r, self.start[1] + r),
                       "disk", colour="tab:green")
        return (*(Region("obstacle", (x0, y0), (x1, y1), colour="0.35") for x0, y0, x1, y1 in self.obstacles), start)


def make() -> Obstacle2D:
    low, high = arena2d.action_bounds(3)
    return Obstacle2D(low, high, (0.0, 0.0), (1.0, 1.0))
