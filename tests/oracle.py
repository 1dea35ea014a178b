"""The paper's insertion rule one candidate at a time: the oracle the data-parallel rule
(`mqd_jax.core.insertion.parallel_rule`) is tested against bit for bit. Both take each candidate's step with
`insertion.decide`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mqd_jax.core import batching, insertion, neighbours
from mqd_jax.core.insertion import AddStatus, Insertion
from mqd_jax.core.repertoire import Repertoire


def _nearest_remaining(behavior: jax.Array, behaviors: jax.Array, valid: jax.Array, qualities: jax.Array,
                       victim_slot: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Squared distance, slot and quality of the pre-generation skill nearest to behavior[d] among those
    victim_slot[P] has not replaced (inf if there is none); behaviors: [C, d], valid, qualities: [C]."""
    d = jnp.where(valid & ~insertion.replaced(victim_slot, valid.shape[0]),
                  neighbours.sq_dists(behavior[None], behaviors), jnp.inf)
    d, j = neighbours.min_with_index(d, jnp.arange(valid.shape[0])[None])
    return d[0], j[0], qualities[j[0]]


def sequential_rule(rep: Repertoire, behaviors: jax.Array, near_d: jax.Array, near_i: jax.Array,
                     d_cand: jax.Array, qualities: jax.Array, usable: jax.Array, t_dist: jax.Array) -> Insertion:
    """Runs the insertion rule candidate by candidate; writes nothing yet.

    near_d, near_i: [P, M] each candidate's M nearest pre-generation skills,
    ascending (squared distance, slot; inf and -1 where there are fewer);
    d_cand: [P, P] squared distances between candidates; usable: [P] the
    candidates to insert. The loop's state is O(P), so it batches well under vmap.
    """
    capacity, pop = rep.capacity, d_cand.shape[0]
    t2 = t_dist**2
    near_q = rep.qualities[jnp.maximum(near_i, 0)]
    cands = jnp.arange(pop)

    def step(i: jax.Array, s: Insertion) -> Insertion:
        count = (s.status == AddStatus.ADDED).sum()
        # The nearest pre-generation skill still there: the first listed one not replaced, else a full search.
        listed = near_i[i]
        still_there = (listed >= 0) & ~(listed[:, None] == s.victim_slot[None]).any(1)
        first = jnp.argmax(still_there)
        quick = (jnp.where(still_there.any(), near_d[i, first], jnp.inf), listed[first], near_q[i, first])
        # All M listed skills were replaced and the next one may be within t_dist.
        need_all = ~still_there.any() & (near_d[i, -1] <= t2)
        d_old, slot_old, q_old = batching.rare_cond(
            need_all, lambda *a: _nearest_remaining(*a[:-1]), lambda *a: a[-1],
            behaviors[i], rep.behaviors, rep.valid, rep.qualities, s.victim_slot, quick)
        # The nearest skill written earlier in this generation, the lowest slot among equally near ones.
        d_row = jnp.where(s.alive, d_cand[i], jnp.inf)
        d_new = d_row.min()
        j_new = jnp.argmin(jnp.where(d_row == d_new, s.slot, capacity))
        slot_new = s.slot[j_new]
        # Nearest by (distance, slot), as a scan over the repertoire's slots would find.
        nearest_is_new = (d_new < d_old) | ((d_new == d_old) & (slot_new < slot_old))
        status, slot_i, replace = insertion.decide(nearest_is_new, d_new, slot_new, qualities[jnp.maximum(j_new, 0)],
                                                   d_old, slot_old, q_old, qualities[i], usable[i], count, rep.count,
                                                   capacity, t2)
        # Whole-row selects rather than scatters: P is small, and they batch without a gather.
        at_i = cands == i
        return Insertion(
            status=jnp.where(at_i, status, s.status),
            slot=jnp.where(at_i, slot_i, s.slot),
            alive=jnp.where(at_i, (status == AddStatus.ADDED) | replace,
                            s.alive & ~((cands == j_new) & replace & nearest_is_new)),
            victim_slot=jnp.where(at_i, jnp.where(replace & ~nearest_is_new, slot_old, -1), s.victim_slot),
            victim_candidate=jnp.where(at_i, jnp.where(replace & nearest_is_new, j_new, -1), s.victim_candidate),
            rounds=s.rounds + 1,
        )

    none = jnp.full(pop, -1, jnp.int32)
    init = Insertion(status=jnp.zeros(pop, jnp.int32), slot=jnp.zeros(pop, jnp.int32), alive=jnp.zeros(pop, bool),
                     victim_slot=none, victim_candidate=none, rounds=jnp.int32(0))
    return jax.lax.fori_loop(0, pop, step, init)
