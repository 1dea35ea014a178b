"""Issue 68's leads measured and not kept (0.22): the network and a `LocalLinear` fit as two members of one
surrogate, or `LocalLinear` alone behind the network's gate ("both", "both:only=1"); `LocalLinear` with its fit's
weighted residual spread s as two members c +- s ("spread"), which `Diverse`'s optimism reads.

    python experiments/lead_members.py --tasks obstacle2d object2d --seeds 10 --compositions qd both
    python experiments/lead_members.py --tasks object2d --seeds 10 --compositions qd both:only=1
    python experiments/lead_members.py --tasks obstacle2d object2d --seeds 10 --compositions qd spread

`sample_efficiency.py` with these compositions added ("both": `"mqd"`'s surrogate with a `LocalLinear` member
beside the network's, both behind its gate; "spread": "local" with the spread as members). Removed after
measuring: docs/results.md gives the figures.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import sample_efficiency as se

from mqd_jax import Config
from mqd_jax.core import archive as archive_lib
from mqd_jax.core.task import Task
from mqd_jax.surrogate import model
from mqd_jax.surrogate.local import LocalLinear, spd_solve
from mqd_jax.surrogate.surrogate import Surrogate


@dataclasses.dataclass(frozen=True)
class Both(Surrogate):
    """The network's members and a `LocalLinear` member on the latest rollouts (kept in the state's `rollouts`,
    the network training on the repertoire); `only_local`: the local member alone, behind the gate."""

    local: LocalLinear = dataclasses.field(default_factory=LocalLinear)
    only_local: bool = False

    def init(self, key: jax.Array, task: Task, capacity: int) -> Any:
        return super().init(key, task, capacity).replace(rollouts=self.local.init(key, task, capacity))

    def members(self, state: Any, actions: jax.Array, task: Task, inputs: jax.Array | None = None) -> jax.Array:
        b, q = self.local.predict(state.rollouts, actions, task)
        own = jnp.concatenate([b, q[:, None]], -1)[None]
        return own if self.only_local else jnp.concatenate([super().members(state, actions, task, inputs), own], 0)

    def observe(self, key: jax.Array, state: Any, actions: jax.Array, rollout: jax.Array, evaluated: Any,
                task: Task, params: Any, features: jax.Array | None = None) -> Any:
        new = super().observe(key, state, actions, rollout, evaluated, task, params, features)
        return new.replace(rollouts=archive_lib.push(state.rollouts, actions, evaluated.behaviors,
                                                     evaluated.qualities, evaluated.usable))


@dataclasses.dataclass(frozen=True)
class Spread(LocalLinear):
    """`LocalLinear` whose members are its fit c plus and minus s, the weighted RMS of the fit's residuals."""

    def members(self, state: Any, actions: jax.Array, task: Task) -> jax.Array:
        x = model.normalize_actions(actions, task)
        xs = model.normalize_actions(state.actions, task)
        ys = jnp.concatenate([state.behaviors, state.qualities[:, None]], axis=-1)
        filled = jnp.arange(xs.shape[0]) < state.total
        searched = jax.lax.stop_gradient(x)
        sq = (searched ** 2).sum(-1)[:, None] + (xs ** 2).sum(-1)[None] - 2.0 * searched @ xs.T
        k = min(self.neighbours or 4 * (task.action_dim + 1), xs.shape[0])
        _, rows = jax.lax.top_k(jnp.where(filled, -sq, -jnp.inf), k)
        z = xs[rows] - x[:, None]
        sq_r, held = (z ** 2).sum(-1), filled[rows]
        farthest = jax.lax.stop_gradient(jnp.where(held, sq_r, 0.0).max(-1, keepdims=True))
        w = jnp.where(held, jnp.clip(1.0 - (sq_r / (farthest * 1.002 + 1e-24)) ** 1.5, 0.0, 1.0) ** 3, 0.0)
        z = jnp.concatenate([jnp.ones_like(z[..., :1]), z], axis=-1)
        penalty = self.ridge * jnp.ones(z.shape[-1]).at[0].set(1e-6)
        gram = jnp.einsum("nki,nk,nkj->nij", z, w, z) + jnp.diag(penalty)
        coefficients = spd_solve(gram, jnp.einsum("nki,nk,nkj->nij", z, w, ys[rows]))
        residuals = ys[rows] - jnp.einsum("nki,nij->nkj", z, coefficients)  # [N, k, d + 1]
        s = jnp.sqrt((w[..., None] * residuals ** 2).sum(1) / jnp.maximum(w.sum(1), 1e-12)[:, None])
        return jnp.stack([coefficients[:, 0] + s, coefficients[:, 0] - s])


def configured(spec: str, task: str, generations: int | None = None) -> Config:
    """`sample_efficiency.configured`, with "both[:only=1]" and "spread"."""
    name, _, rest = spec.partition(":")
    if name not in ("both", "spread"):
        return plain(spec, task, generations)
    cfg = plain("mqd" if name == "both" else "local", task, generations)
    surrogate = cfg.emitter.surrogate
    if name == "both":
        surrogate = Both(**{f.name: getattr(surrogate, f.name) for f in dataclasses.fields(Surrogate)},
                         only_local=rest == "only=1")
    else:
        surrogate = Spread()
    return dataclasses.replace(cfg, algorithm=dataclasses.replace(cfg.emitter, surrogate=surrogate),
                               algorithm_options={})


plain = se.configured
se.COMPOSITIONS = (*se.COMPOSITIONS, "both", "spread")
se.configured = configured

if __name__ == "__main__":
    se.main()
