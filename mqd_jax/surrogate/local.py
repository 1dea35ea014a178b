"""A surrogate without a network: each candidate's outcome fitted afresh from the rollouts nearest to it.

`LocalLinear()` keeps the latest `buffer` usable rollouts (a ring buffer, filled by `observe` after every
generation, warm-up included) and predicts a candidate a by a weighted linear fit to its `neighbours` nearest
rollouts in normalized action space (locally weighted regression, as LOESS): weights w_j = (1 - (r_j / r_k)^3)^3
of the distance r_j over the k-th nearest's r_k (tricube), then

    [c, J] = argmin  sum_j w_j |y_j - c - J (a_j - a)|^2 + ridge |J|^2,    prediction c

for y = (behavior, quality). A child lies a small step from its parent, among rollouts of its parent's
neighbourhood (the parent's own, its siblings' and earlier children's); the fit reads the map there, at the
step's scale, where a network fitted over the whole action space smooths it (issue 68's lead "learn relative
to the parent"; docs/results.md measures it). It needs no training (`fit` keeps the state): its cost is the
search for neighbours, [N, buffer] distances per prediction. It keeps the surrogate protocol
(`mqd_jax.surrogate.protocol`), differentiable in the actions (steering and `adapt(..., "model")`), with the
optional `observe`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from mqd_jax.core import archive as archive_lib
from mqd_jax.core.checks import is_int, is_real
from mqd_jax.core.emitter import Evaluated
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.task import Task
from mqd_jax.surrogate import model


def spd_solve(a: jax.Array, b: jax.Array) -> jax.Array:
    """x with a x = b for symmetric positive definite a [..., m, m] and b [..., m, r]: Gauss-Jordan elimination
    without pivoting, unrolled over m, in elementwise operations (no call into a linear-algebra library: XLA's
    CPU one stalled under a vmapped batch of runs)."""
    m = a.shape[-1]
    for i in range(m):
        pivot = a[..., i:i + 1, i:i + 1]
        row_a, row_b = a[..., i:i + 1, :] / pivot, b[..., i:i + 1, :] / pivot
        column = a[..., :, i:i + 1]
        at_pivot = (jnp.arange(m) == i)[:, None]
        a = jnp.where(at_pivot, row_a, a - column * row_a)
        b = jnp.where(at_pivot, row_b, b - column * row_b)
    return b


@dataclasses.dataclass(frozen=True)
class LocalLinear:
    """Locally weighted linear regression on the latest rollouts (module doc).

    Attributes:
      neighbours: the rollouts each fit reads (at most `buffer`); None: 4 (n + 1) for n action dimensions (four
        per coefficient).
      ridge: the penalty on the slopes J, in normalized action units (the intercept is not penalized).
      buffer: the latest usable rollouts kept.
    """

    neighbours: int | None = None
    ridge: float = 1e-3
    buffer: int = 4096

    def __post_init__(self) -> None:
        if self.neighbours is not None and not (is_int(self.neighbours) and self.neighbours >= 2):
            raise ValueError(f"LocalLinear.neighbours={self.neighbours!r} is invalid: expected None or an int >= 2")
        if not (is_real(self.ridge) and self.ridge > 0):
            raise ValueError(f"LocalLinear.ridge={self.ridge!r} is invalid: expected a finite float > 0")
        if not (is_int(self.buffer) and self.buffer >= 2):
            raise ValueError(f"LocalLinear.buffer={self.buffer!r} is invalid: expected an int >= 2")

    def init(self, key: jax.Array, task: Task, capacity: int) -> archive_lib.Archive:
        """The empty buffer (`archive.Archive` of `buffer` rows)."""
        return archive_lib.Archive.empty(self.buffer, task.action_dim, task.behavior_dim)

    def fit(self, key: jax.Array, state: archive_lib.Archive, repertoire: Repertoire, task: Task,
            params: tuple) -> tuple[archive_lib.Archive, jax.Array]:
        """Nothing to train: the state as it is, loss NaN."""
        return state, jnp.float32(jnp.nan)

    def observe(self, key: jax.Array, state: archive_lib.Archive, actions: jax.Array, rollout: jax.Array,
                evaluated: Evaluated, task: Task, params: tuple,
                features: jax.Array | None = None) -> archive_lib.Archive:
        """The buffer with a generation's usable rollouts of actions [P, n] pushed (the oldest overwritten)."""
        return archive_lib.push(state, actions, evaluated.behaviors, evaluated.qualities, evaluated.usable)

    def predict(self, state: archive_lib.Archive, actions: jax.Array, task: Task) -> tuple[jax.Array, jax.Array]:
        """Behaviors [..., d] and qualities [...] of actions [..., n]: each a fit to its nearest rollouts (module
        doc); zeros while the buffer is empty."""
        flat = actions.reshape(-1, actions.shape[-1])
        x = model.normalize_actions(flat, task)  # [N, n]
        xs = model.normalize_actions(state.actions, task)  # [A, n]
        ys = jnp.concatenate([state.behaviors, state.qualities[:, None]], axis=-1)  # [A, d + 1]
        filled = jnp.arange(xs.shape[0]) < state.total
        # Squared distances by one product (not an [N, A, n] difference); the search is not differentiated.
        searched = jax.lax.stop_gradient(x)
        sq = (searched ** 2).sum(-1)[:, None] + (xs ** 2).sum(-1)[None] - 2.0 * searched @ xs.T
        k = min(self.neighbours or 4 * (task.action_dim + 1), xs.shape[0])
        _, rows = jax.lax.top_k(jnp.where(filled, -sq, -jnp.inf), k)  # [N, k]
        z = xs[rows] - x[:, None]  # [N, k, n], differentiable in x
        # (r / r_k)^3 from squared distances: differentiable where a neighbour is the candidate itself (r = 0)
        sq_r, held = (z ** 2).sum(-1), filled[rows]
        farthest = jax.lax.stop_gradient(jnp.where(held, sq_r, 0.0).max(-1, keepdims=True))
        w = jnp.where(held, jnp.clip(1.0 - (sq_r / (farthest * 1.002 + 1e-24)) ** 1.5, 0.0, 1.0) ** 3, 0.0)
        z = jnp.concatenate([jnp.ones_like(z[..., :1]), z], axis=-1)  # [N, k, n + 1]
        penalty = self.ridge * jnp.ones(z.shape[-1]).at[0].set(1e-6)  # the intercept all but free
        gram = jnp.einsum("nki,nk,nkj->nij", z, w, z) + jnp.diag(penalty)
        coefficients = spd_solve(gram, jnp.einsum("nki,nk,nkj->nij", z, w, ys[rows]))  # [N, n + 1, d + 1]
        y = coefficients[:, 0].reshape(*actions.shape[:-1], -1)
        return y[..., :-1], y[..., -1]
