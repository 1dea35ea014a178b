"""`Diverse`, the acquisition rule of `"mqd"`: a fixed number of candidates chosen one at a time by optimistic
(UCB) gain against an imagined repertoire that already holds the predicted behaviors of those chosen, so that one
generation does not spend rollouts on near-duplicates; greedily (`greedy_diverse`) or in rounds of picks that
cannot interact (`rounds_diverse`), the same choice. The scores it reads, `Judged`, and the rule protocol are
`mqd_jax.emitters.acquisition`'s.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import grid
from mqd_jax.core import neighbours as neighbours_lib
from mqd_jax.core.checks import is_int, is_real
from mqd_jax.core.params import Params
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.emitters.acquisition import Judged, check_pool_factor, ranked_result


def parent_factor(judged: Judged, weight: float) -> jax.Array | float:
    """[N] (parent's novelty / the pool's mean parent novelty) ** weight: 1 for a candidate without a parent, and
    for all where `weight` is 0, the pool names no parents or their mean novelty is not positive."""
    if weight == 0 or judged.parent_novelty is None:
        return 1.0
    novelty = judged.parent_novelty
    mean = jnp.nanmean(novelty)
    return jnp.where(jnp.isnan(novelty) | ~(mean > 0), 1.0, novelty / mean) ** weight


SELECTIONS = ("auto", "greedy", "rounds")  # Diverse's ways to choose


# "auto" chooses in rounds from this many rows on (a pool of 8 x that), one at a time below: on a 2-core CPU the
# rounds cost 1.4 ms at 100 rows against the greedy steps' 0.7, 0.4x them at 1,024 and 0.2x at 4,096
# (experiments/selection_timing.py), but search less well: at 1,024, 2D Obstacle's coverage after 100
# generations 0.978 against greedy's 0.995; at 4,096 it catches up by 40 generations (docs/design.md,
# "Batch-diverse, optimistic acquisition"). Below, runs repeat earlier versions' bit for bit.
ROUNDS_FROM = 2048


# Pool neighbours `pool_neighbours` reads per row of grid cells (three rows in two dimensions or more, one row of
# three cells in one): what a candidate of `rounds_diverse` sees of the pool, whatever the pool's size.
WINDOW = 32


def pool_neighbours(points: jax.Array, ok: jax.Array, t_dist: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Each point's neighbours among points [N, d] (those ok [N]) that may lie within `t_dist` of it: ids [N, K]
    and whether each is one (bool [N, K]; never the point itself), K = 3 x WINDOW, found without an [N, N] matrix
    in a grid of cells (`grid`): each of a point's three runs of adjacent cells (one in one dimension) is read for
    WINDOW places (3 x WINDOW in one dimension). Exact where no run holds more; otherwise the first WINDOW of each
    run (the rest unseen)."""
    return grid.in_cells(3 * WINDOW if points.shape[1] == 1 else WINDOW, grid.cells(points, ok, t_dist))


def _diverse_terms(judged: Judged, beta: float, neighbours: int, parent_weight: float
                   ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array, jax.Array]:
    """What both diverse selections read of a judged pool: (finite [N], optimism beta x spread [N], near [N, M]
    ascending, the parent factor [N] or 1, plausible [N]); ValueError where `neighbours` asks for more columns
    than judged."""
    columns = 0 if judged.neighbours is None else judged.neighbours.shape[1]
    if neighbours > 1 and columns < neighbours:
        raise ValueError(f"Diverse.neighbours={neighbours} needs the distances to that many nearest skills; "
                         f"the model's judgement has {columns} (ModelEmitter.k)")
    optimism = beta * judged.spread
    finite = jnp.isfinite(judged.behaviors).all(axis=1) & jnp.isfinite(judged.qualities) & jnp.isfinite(optimism)
    near = judged.distance[:, None] if neighbours == 1 else judged.neighbours[:, :neighbours]
    return finite, optimism, near, parent_factor(judged, parent_weight), judged.plausible


def _tiers(near: jax.Array, nearest_quality: jax.Array, free: jax.Array, preferred_is_improver: jax.Array | bool,
           q: jax.Array, finite: jax.Array, optimism: jax.Array, factor: jax.Array | float, wanted: jax.Array,
           plausible: jax.Array, t_dist: jax.Array, quality_margin: jax.Array | float, cap: float = 0.0
           ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(tier [N] (-1 for a candidate taken), value [N], opens [N]) of a diverse selection's step: first the wanted,
    then the preferred (openers, or on a quality step the improvers), then the plausible; within a tier by value
    (an opener's optimistic mean distance to its nearest imagined skills, at most `cap` x t_dist where `cap` > 0,
    times the parent factor, else the predicted improvement over its nearest)."""
    opens = finite & (near[:, 0] + optimism > t_dist)
    improves = finite & ~opens & (q - nearest_quality > quality_margin)
    known = jnp.isfinite(near)
    count = known.sum(axis=1)
    mean = jnp.where(count > 0, jnp.where(known, near, 0.0).sum(axis=1) / jnp.maximum(count, 1), jnp.inf)
    if cap:  # a predicted opener's distance counts up to cap x t_dist: farther predictions err the most
        mean = jnp.minimum(mean, cap * t_dist)
    preferred = jnp.where(preferred_is_improver, improves, opens)
    value = jnp.where(finite, jnp.nan_to_num(jnp.where(opens, (mean + optimism) * factor, q - nearest_quality)),
                      -jnp.inf)
    tier = jnp.where(free, 4 * wanted.astype(jnp.int32) + 2 * preferred.astype(jnp.int32)
                     + plausible.astype(jnp.int32), -1)
    return tier, value, opens


def greedy_diverse(judged: Judged, wanted: jax.Array, t_dist: jax.Array, beta: float, num: int,
                   neighbours: int = 1, parent_weight: float = 0.0, quality_share: float = 0.0,
                   quality_margin: float | jax.Array = 0.0, cap: float = 0.0) -> jax.Array:
    """[num] pool rows chosen one at a time against an imagined repertoire; the first chosen first.

    Each step takes, among the candidates not yet chosen, first those the
    inner emitter wants, then those predicted to open a niche, i.e. whose
    optimistic distance dist~ + beta * spread to the nearest behavior of the
    repertoire and of the wanted candidates chosen so far exceeds `t_dist`,
    by the largest optimistic mean distance to the `neighbours` nearest such
    behaviors (1: the distance to the nearest; more: a novelty, which looks past
    the nearest one to how crowded the predicted behavior's surroundings are,
    needing `judged.neighbours` of at least that many columns, else ValueError;
    counted up to `cap` x t_dist where `cap` > 0); then the rest by
    the largest predicted quality improvement over that nearest behavior. In
    each of these tiers the candidates judged likely usable (`Judged.plausible`)
    come first. NaN predictions come last.

    m = round(`quality_share` x num) of the steps, spread evenly over the batch
    (step i is one where (i + 1) m // num > i m // num, so that a prefix of the
    rows holds its share of them too), are quality steps: they take first the
    candidates predicted not to open a niche but to beat the quality of their
    nearest behavior by more than `quality_margin` (quality units), by the
    largest predicted improvement, and only then the others as above. Without
    them, a rule that always finds enough predicted openers never spends a
    rollout on a better skill for a niche it holds.
    """
    b, q = judged.behaviors, judged.qualities
    finite, optimism, near, factor, plausible = _diverse_terms(judged, beta, neighbours, parent_weight)  # [N, M]

    def choose(carry: tuple[jax.Array, jax.Array, jax.Array],
               quality_step: jax.Array) -> tuple[tuple[jax.Array, ...], jax.Array]:
        near, nearest_quality, free = carry
        # A quality step prefers the improvers (by their improvement, as non-openers are ranked anyway).
        tier, value, _ = _tiers(near, nearest_quality, free, quality_step, q, finite, optimism, factor, wanted,
                                plausible, t_dist, quality_margin, cap)
        best = tier == tier.max()
        pick = jnp.argmax(jnp.where(best, value, -jnp.inf))
        pick = jnp.where(best[pick], pick, jnp.argmax(best)).astype(jnp.int32)  # all of the tier at -inf: the first
        # A wanted candidate is rolled out: later ones are judged against its predicted behavior too.
        to_pick = jnp.sqrt(neighbours_lib.sq_dists(b, b[pick][None])[:, 0])
        # Insert to_pick into each sorted row: column j becomes max(to_pick, old column j - 1) where to_pick is
        # below it (no sort; a NaN distance changes nothing).
        below = jnp.concatenate([jnp.full_like(near[:, :1], -jnp.inf), near[:, :-1]], axis=1)
        merged = jnp.where(to_pick[:, None] < near, jnp.maximum(to_pick[:, None], below), near)
        closest = wanted[pick] & (to_pick < near[:, 0])
        return (jnp.where(wanted[pick], merged, near), jnp.where(closest, q[pick], nearest_quality),
                free.at[pick].set(False)), pick

    start = (near, judged.nearest_quality, jnp.ones_like(wanted))
    steps, quality_count = np.arange(num), round(quality_share * num)
    quality_steps = jnp.asarray((steps + 1) * quality_count // num > steps * quality_count // num)
    _, rows = jax.lax.scan(choose, start, quality_steps, unroll=4)
    return rows


def rounds_diverse(judged: Judged, wanted: jax.Array, t_dist: jax.Array, beta: float, num: int, rounds: int,
                   neighbours: int = 1, parent_weight: float = 0.0, quality_share: float = 0.0,
                   quality_margin: float | jax.Array = 0.0, cap: float = 0.0) -> jax.Array:
    """[num] pool rows chosen in at most `rounds` data-parallel rounds (non-maximum suppression; they stop once the
    budget is full or a round takes none), then filled by score; the
    first chosen first. `greedy_diverse`'s choice made parallel in the pool: its order, tiers and values, not its
    one-at-a-time steps.

    Each round ranks the free candidates as a greedy step would (wanted, then predicted openers, then plausible,
    then by value) and takes every candidate of the first tier left that ranks above each free candidate of its
    conflicts (those whose predicted behavior lies within `t_dist` of its own), at most what is left of the
    budget, best first:
    the candidates taken in one round never conflict, as a greedy choice would not take the second of two
    openers within `t_dist`. The wanted ones taken enter the imagined repertoire (their predicted behaviors),
    so the next round judges the rest against them. Spatial work is bounded: each candidate reads only the
    3 x `WINDOW` pool neighbours `pool_neighbours` finds once per generation in a grid of cells (`grid`; its
    conflicts and the imagined skills it sees among them: exact where no run of cells holds more than `WINDOW`).
    A round costs O(pool x WINDOW) (and a sort where more than the budget left win it); `rounds` rounds
    replace `num` sequential steps. `quality_share` of the rows are the quality steps' (improvers
    first, placed where `greedy_diverse` places its quality steps).
    """
    b, q = judged.behaviors, judged.qualities
    size = b.shape[0]
    finite, optimism, near, factor, plausible = _diverse_terms(judged, beta, neighbours, parent_weight)
    others, seen = pool_neighbours(b, finite, t_dist)
    gap = jnp.sqrt(sum((b[:, None, k] - b[others, k]) ** 2 for k in range(b.shape[1])))
    conflict = seen & (gap <= t_dist)
    wanted_seen = seen & wanted[others]
    quality_count = round(quality_share * num)
    openers = num - quality_count

    def before(tier_a: jax.Array, value_a: jax.Array, a: jax.Array, tier_b: jax.Array, value_b: jax.Array,
               b_: jax.Array) -> jax.Array:
        """Whether candidate a ranks before candidate b (tier, then value, then the lower index): no sort."""
        return (tier_a > tier_b) | ((tier_a == tier_b) & ((value_a > value_b) | ((value_a == value_b) & (a < b_))))

    def one_round(carry: tuple[jax.Array, ...]) -> tuple[jax.Array, ...]:
        round_, _, near, nearest_quality, free, position, taken_in, taken_tier, taken_value = carry
        tier, value, _ = _tiers(near, nearest_quality, free, False, q, finite, optimism, factor, wanted,
                                plausible, t_dist, quality_margin, cap)
        mine = jnp.arange(size)[:, None]
        beaten = conflict & free[others] & before(tier[others], value[others], others, tier[:, None],
                                                  value[:, None], mine)
        take = free & ~beaten.any(axis=1) & (tier == tier.max())  # as greedy steps, a tier after another

        def best_of(take: jax.Array) -> jax.Array:  # more than the budget left: its best, by one sort
            rank = jnp.argsort(jnp.lexsort((-value, -tier, ~take)), stable=True)
            return take & (rank < openers - position)

        take = jax.lax.cond(take.sum() > openers - position, best_of, lambda t: t, take)
        taken_in = jnp.where(take, round_, taken_in)
        taken_tier, taken_value = jnp.where(take, tier, taken_tier), jnp.where(take, value, taken_value)
        # The wanted ones taken are imagined skills for the rest: the nearest of them merged into each row.
        from_taken = jnp.where(wanted_seen & take[others], gap, jnp.inf)
        nearest = jnp.argmin(from_taken, axis=1)
        d_taken = jnp.take_along_axis(from_taken, nearest[:, None], axis=1)[:, 0]
        if near.shape[1] == 1:
            merged = jnp.minimum(near, d_taken[:, None])
        else:
            merged = jnp.sort(jnp.concatenate([near, from_taken], axis=1), axis=1)[:, :near.shape[1]]
        nearest_quality = jnp.where(d_taken < near[:, 0], q[others[jnp.arange(size), nearest]], nearest_quality)
        return (round_ + 1, take.any(), merged, nearest_quality, free & ~take, position + take.sum(dtype=jnp.int32),
                taken_in, taken_tier, taken_value)

    def more(carry: tuple[jax.Array, ...]) -> jax.Array:
        """Rounds left, a round before took some, and budget left."""
        return (carry[0] < rounds) & carry[1] & (carry[5] < openers)

    none = jnp.full(size, rounds, jnp.int32)
    start = (jnp.int32(0), jnp.bool_(True), near, judged.nearest_quality, jnp.ones(size, bool), jnp.int32(0), none,
             jnp.zeros(size, jnp.int32), jnp.zeros(size))
    _, _, near, nearest_quality, free, _, taken_in, taken_tier, taken_value = jax.lax.while_loop(
        more, one_round, start)
    # The openers' rows: by round taken, each round best first; then the best of the rest by a last ranking.
    tier, value, _ = _tiers(near, nearest_quality, free, False, q, finite, optimism, factor, wanted, plausible,
                            t_dist, quality_margin, cap)
    chosen = jnp.lexsort((-jnp.where(free, value, taken_value), -jnp.where(free, tier, taken_tier), taken_in))
    rows = chosen[:openers]
    if quality_count:
        left = jnp.ones(size, bool).at[rows].set(False)
        tier, value, _ = _tiers(near, nearest_quality, left, True, q, finite, optimism, factor, wanted,
                                plausible, t_dist, quality_margin, cap)
        extra = jnp.lexsort((-value, -tier))[:quality_count]
        steps = np.arange(num)
        is_quality = (steps + 1) * quality_count // num > steps * quality_count // num
        slots = np.zeros(num, np.int64)
        slots[is_quality], slots[~is_quality] = np.arange(openers, num), np.arange(openers)
        rows = jnp.concatenate([rows, extra])[slots]
    return rows.astype(jnp.int32)


@dataclasses.dataclass(frozen=True)
class Diverse:
    """Batch-diverse optimistic ranking: of `pool_factor` x num candidates, roll out num chosen one at a time
    (`greedy_diverse`, optimism `beta` x the ensemble's spread, ranked by the mean distance to the `neighbours`
    nearest imagined or real skills: 1, the nearest; at most `ModelEmitter.k`; times the parent's relative
    novelty to the power `parent_weight`: 0, not read; a `quality_share` of the steps prefer predicted quality
    improvements of held niches larger than `quality_margin` x the standard deviation of the repertoire's
    qualities; an opener's distance counted up to `cap` x t_dist, 0: no cap). `selection`: "greedy" (one at a
    time, `greedy_diverse`: the oracle of what diverse means), "rounds" (`rounds_diverse`: `rounds` data-parallel
    rounds, then filled by score), or "auto": rounds where `num` >= `ROUNDS_FROM` (where they are faster), else
    greedy (so smaller runs repeat earlier versions' bit for bit)."""

    pool_factor: int = 8
    beta: float = 1.0
    neighbours: int = 1
    parent_weight: float = 0.0
    quality_share: float = 0.0
    quality_margin: float = 0.0
    selection: str = "auto"
    rounds: int = 16
    cap: float = 0.0

    def __post_init__(self) -> None:
        check_pool_factor(self)
        for name in ("beta", "parent_weight", "quality_margin", "cap"):
            value = getattr(self, name)
            if not (is_real(value) and value >= 0):
                raise ValueError(f"Diverse.{name}={value!r} is invalid: expected a finite float >= 0")
        if not (is_int(self.neighbours) and self.neighbours >= 1):
            raise ValueError(f"Diverse.neighbours={self.neighbours!r} is invalid: expected an int >= 1")
        if not (is_real(self.quality_share) and 0 <= self.quality_share <= 1):
            raise ValueError(f"Diverse.quality_share={self.quality_share!r} is invalid: expected a float in [0, 1]")
        if self.selection not in SELECTIONS:
            raise ValueError(f"Diverse.selection={self.selection!r} is invalid: expected one of {SELECTIONS}")
        if not (is_int(self.rounds) and self.rounds >= 1):
            raise ValueError(f"Diverse.rounds={self.rounds!r} is invalid: expected an int >= 1")

    def pool_size(self, num: int) -> int:
        return num * self.pool_factor

    def select(self, key: jax.Array, state: Any, judged: Judged, repertoire: Repertoire, wanted: jax.Array,
               params: Params, num: int) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Rows [num] of the pool kept (first chosen first), their rollout mask [num] and how many candidates were
        turned down."""
        margin = 0.0
        if self.quality_margin:  # scale-free: in standard deviations of the repertoire's qualities (0 while empty)
            margin = self.quality_margin * jnp.std(repertoire.qualities, where=repertoire.valid)
        if self.selection == "rounds" or (self.selection == "auto" and num >= ROUNDS_FROM):
            top = rounds_diverse(judged, wanted, params.t_dist, self.beta, num, self.rounds, self.neighbours,
                                 self.parent_weight, self.quality_share, jnp.nan_to_num(margin), self.cap)
        else:
            top = greedy_diverse(judged, wanted, params.t_dist, self.beta, num, self.neighbours, self.parent_weight,
                                 self.quality_share, jnp.nan_to_num(margin), self.cap)
        return ranked_result(top, wanted)

