"""Several emitters in one generation, each proposing its share of the rollouts (as QDax's `MultiEmitter` and
pyribs' scheduler over several emitters).

    SideBySide((presets.mqd(), presets.qd()))                          # half each
    SideBySide((presets.mqd(), presets.qd()), shares=(0.75, 0.25))    # fixed shares
    SideBySide((presets.mqd(), presets.qd()), shares=Fallback())      # adaptive: pursuit between the two

With fixed shares member i proposes round(share_i x num) rows (the last member the rest), every member at least
one. With a share (`parts.Share`, such as `Fallback()`: adaptive pursuit toward whichever member's rollouts have
recently opened more niches; two members), each member proposes `num` rows and the generation takes the first
round(share x num) of the first member's, then the second member's first rows: a member whose best rows come
first (a model emitter with a ranking rule) keeps its best. Each member's `update` sees its own proposal, the rows
the generation did not take as not rolled out (`AddStatus.SKIPPED`). A share that reads the model's predictions
(`StepAside`) has none here.

Metrics: each member's, prefixed by its name (`names`; default its class's name in lower case, with its index
where two are alike): "modelemitter.discarded"; with a share, `share` (the first member's this generation).
`adapt(..., "model")` uses the first member that has a model (`Emitter.forward_model`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from mqd_jax.core import pytree
from mqd_jax.core.emitter import Emitter, Evaluated, Proposal, init_emitter
from mqd_jax.core.params import Params
from mqd_jax.core.repertoire import AddStatus, Repertoire
from mqd_jax.core.task import Task
from mqd_jax.emitters.parts import is_share


@pytree.dataclass
class SideBySideState:
    """Attributes:
      members: tuple of the members' states.
      share: the share's state, or () with fixed shares.
    """

    members: tuple[Any, ...]
    share: Any = ()


@dataclasses.dataclass(frozen=True)
class SideBySide(Emitter):
    """Runs `members` side by side in each generation (module doc).

    Attributes:
      members: the emitters (at least two).
      shares: fixed fractions of the rollouts, one per member (> 0, summing to 1), or a share of the first of two
        members (`parts.Share`, such as `Fallback()`); default: equal fixed shares.
      names: the members' metric prefixes, distinct; default: their classes' names in lower case.
    """

    members: tuple[Emitter, ...]
    shares: Any = None
    names: tuple[str, ...] | None = None

    sized = True

    def __post_init__(self) -> None:
        members = self.members
        if not (isinstance(members, tuple) and len(members) >= 2 and all(isinstance(m, Emitter) for m in members)):
            raise ValueError(f"SideBySide.members={members!r} is invalid: expected a tuple of two or more Emitters")
        if is_share(self.shares):
            if len(members) != 2:
                raise ValueError(f"SideBySide.shares={self.shares!r} is invalid with {len(members)} members: a share "
                                 "divides the rows between two")
        elif self.shares is not None and not (
                isinstance(self.shares, tuple) and len(self.shares) == len(members)
                and all(isinstance(s, int | float) and not isinstance(s, bool) and s > 0 for s in self.shares)
                and abs(sum(self.shares) - 1.0) < 1e-6):
            raise ValueError(f"SideBySide.shares={self.shares!r} is invalid: expected None, a share (such as "
                             f"Fallback()) or {len(members)} fractions > 0 summing to 1")
        names = self.prefixes
        if len(set(names)) != len(names) or not all(isinstance(n, str) and n for n in names):
            raise ValueError(f"SideBySide.names={self.names!r} is invalid: expected {len(members)} distinct, "
                             "non-empty names")

    @property
    def prefixes(self) -> tuple[str, ...]:
        """The members' metric prefixes."""
        if self.names is not None:
            return tuple(self.names)
        kinds = [type(m).__name__.lower() for m in self.members]
        return tuple(k if kinds.count(k) == 1 else f"{k}{i}" for i, k in enumerate(kinds))

    @property
    def adaptive(self) -> bool:
        return is_share(self.shares)

    def counts(self, num: int) -> tuple[int, ...]:
        """The rows each member proposes for `num` rollouts (fixed shares: theirs, the last the rest; a share:
        `num` each)."""
        if self.adaptive:
            return (num,) * len(self.members)
        shares = self.shares or (1.0 / len(self.members),) * len(self.members)
        first = [round(s * num) for s in shares[:-1]]
        return (*first, num - sum(first))

    def default_params(self) -> tuple[Any, ...]:
        return tuple(m.default_params() for m in self.members)

    def check_params(self, params: tuple[Any, ...]) -> None:
        for member, own in zip(self.members, params, strict=True):
            member.check_params(own)

    def check_run(self, population_size: int, max_generations: int) -> None:
        counts = self.counts(population_size)
        if min(counts) < 1:
            raise ValueError(f"SideBySide.shares={self.shares!r} gives the members {counts} of a population of "
                             f"{population_size}: expected at least 1 each (larger shares, or a larger population)")
        for member, count in zip(self.members, counts, strict=True):
            member.check_run(count, max_generations)

    def check_task(self, task: Task) -> None:
        for member in self.members:
            member.check_task(task)

    def keeps_features(self, task: Task) -> bool:
        return any(m.keeps_features(task) for m in self.members)

    def pool_size(self, num: int) -> int:
        return sum(m.pool_size(c) for m, c in zip(self.members, self.counts(num), strict=True))

    def forward_model(self, state: SideBySideState, task: Task) -> Any:
        """The first member's model that has one (`Emitter.forward_model`), or None."""
        for member, own in zip(self.members, state.members, strict=True):
            found = member.forward_model(own, task)
            if found is not None:
                return found
        return None

    def init(self, key: jax.Array, task: Task, capacity: int) -> SideBySideState:
        members = tuple(init_emitter(m, jax.random.fold_in(key, i), task, capacity)
                        for i, m in enumerate(self.members))
        return SideBySideState(members, self.shares.init(key, task) if self.adaptive else ())

    def _rows(self, state: SideBySideState, num: int) -> list[jax.Array]:
        """For each member, the generation's row each of its proposed rows becomes ([count_i] int32; num where
        it is not taken)."""
        counts = self.counts(num)
        if not self.adaptive:
            starts = [sum(counts[:i]) for i in range(len(counts))]
            return [jnp.arange(s, s + c, dtype=jnp.int32) for s, c in zip(starts, counts, strict=True)]
        first = jnp.round(self.shares.share(state.share) * num).astype(jnp.int32)
        slots = jnp.arange(num, dtype=jnp.int32)
        return [jnp.where(slots < first, slots, num), jnp.where(first + slots < num, first + slots, num)]

    def propose(self, key: jax.Array, state: SideBySideState, repertoire: Repertoire, task: Task, params: Params,
                num: int) -> Proposal:
        proposals = [m.propose(jax.random.fold_in(key, i), own, repertoire, task, params.part(p), c)
                     for i, (m, own, p, c) in enumerate(zip(self.members, state.members, params.emitter,
                                                            self.counts(num), strict=True))]
        rows = self._rows(state, num)

        def placed(get: Any) -> jax.Array:
            """The generation's [num, ...] rows from each member's rows where they are taken."""
            first = get(proposals[0])
            out = jnp.zeros((num, *first.shape[1:]), first.dtype)
            for proposal, at in zip(proposals, rows, strict=True):
                out = out.at[at].set(get(proposal), mode="drop")
            return out

        features = None
        if self.keeps_features(task):
            features = placed(lambda p: task.features(p.actions) if p.features is None else p.features)
        parents = placed(lambda p: jnp.full(p.actions.shape[0], -1, jnp.int32) if p.parents is None
                         else p.parents.astype(jnp.int32))
        return Proposal(placed(lambda p: p.actions), placed(lambda p: p.rollout),
                        tuple(p.info for p in proposals), parents, features)

    def update(self, key: jax.Array, state: SideBySideState, proposal: Proposal, evaluated: Evaluated,
               repertoire: Repertoire, task: Task, params: Params) -> tuple[SideBySideState, dict[str, jax.Array]]:
        num = proposal.actions.shape[0]
        rows = self._rows(state, num)
        members, metrics = [], {}
        for i, (member, own, p, at, prefix) in enumerate(zip(self.members, state.members, params.emitter, rows,
                                                             self.prefixes, strict=True)):
            taken = at < num
            mine = lambda x, at=at, taken=taken: jnp.where(  # noqa: E731
                taken.reshape(-1, *(1,) * (x.ndim - 1)), x[jnp.minimum(at, num - 1)], jnp.zeros((), x.dtype))
            seen = jax.tree.map(mine, evaluated).replace(
                status=jnp.where(taken, evaluated.status[jnp.minimum(at, num - 1)], AddStatus.SKIPPED))
            own_proposal = Proposal(mine(proposal.actions), mine(proposal.rollout), proposal.info[i],
                                    features=None if proposal.features is None else mine(proposal.features))
            new, reported = member.update(jax.random.fold_in(key, i), own, own_proposal, seen, repertoire, task,
                                          params.part(p))
            members.append(new)
            metrics.update({f"{prefix}.{name}": value for name, value in reported.items()})
        share = state.share
        if self.adaptive:
            metrics["share"] = self.shares.share(state.share)
            share = self.shares.learn(state.share, rows[0] < num, jnp.full(evaluated.behaviors.shape, jnp.nan),
                                      evaluated)
        return SideBySideState(tuple(members), share), metrics

    def metrics(self) -> dict[str, Any]:
        own = {"share": jnp.float32} if self.adaptive else {}
        for member, prefix in zip(self.members, self.prefixes, strict=True):
            own.update({f"{prefix}.{name}": dtype for name, dtype in member.metrics().items()})
        return own
