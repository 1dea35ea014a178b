import jax
import jax.numpy as jnp
import numpy as np
import oracle
import pytest
import reference
from compiled import compiled
from hypothesis import given, settings
from hypothesis import strategies as st

from mqd_jax.core import bands, insertion, neighbours, repertoire
from mqd_jax.core.repertoire import AddStatus, Repertoire, insert

NAMES = {AddStatus.SKIPPED: "skipped", AddStatus.ADDED: "added", AddStatus.REPLACED: "replaced",
         AddStatus.REJECTED: "rejected", AddStatus.DROPPED_FULL: "dropped"}
K = 3


def _insert_fn(rep, actions, behaviors, qualities, ok, t_dist):
    # min_prefix 8: a 40-slot repertoire works on prefixes of 8, 10, 20 and 40 slots as it grows.
    return insert(rep, actions, behaviors, qualities, ok, t_dist, K, num_near=2, chunk=8, min_prefix=8)


_insert = jax.jit(_insert_fn)
_banded = jax.jit(lambda *args: _insert_fn(*args))  # a function of its own: jit caches traces per function


def _insert_banded(*args):
    """`_insert` with the nearest skills searched in bands (`bands.near_within`) however small the sizes."""
    saved, bands.BRUTE_FORCE_PAIRS = bands.BRUTE_FORCE_PAIRS, 0
    try:
        return _banded(*args)
    finally:
        bands.BRUTE_FORCE_PAIRS = saved


def _batches(draw_seed: int, generations: int, pop: int, spread: float, lattice: bool = False):
    rng = np.random.default_rng(draw_seed)
    for _ in range(generations):
        # Behaviors on a coarse lattice plus noise: many near-duplicates, so
        # replacements of pre-generation skills and of earlier candidates of the
        # same generation both happen, and the M=2 near lists get exhausted.
        # `lattice`: no noise, on a grid of 1/16 (distances exact in float32): exact ties between skills.
        if lattice:
            b = (rng.integers(0, 6, (pop, 2)) / 16).astype(np.float32)
        else:
            centre = rng.integers(0, 4, (pop, 2)) * spread
            b = (centre + rng.normal(0, spread / 3, (pop, 2))).astype(np.float32)
        q = rng.random(pop).astype(np.float32)
        ok = rng.random(pop) > 0.15
        yield b, q, ok


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), capacity=st.sampled_from([6, 40]), spread=st.sampled_from([0.05, 0.2]),
       lattice=st.booleans(), banded=st.booleans())
def test_insertion_matches_sequential_reference(seed, capacity, spread, lattice, banded):
    """The oracle scans the slots in order: of equally near skills, the lowest slot is the nearest. `banded`: the
    nearest skills are searched in bands along an axis, not among all skills."""
    pop, t_dist = 12, 0.1
    rep = Repertoire.empty(capacity, 1, 2, K + 2)
    ref_b, ref_q = np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
    for b, q, ok in _batches(seed, 4, pop, spread, lattice):
        actions = jnp.asarray(np.arange(pop, dtype=np.float32)[:, None])
        before_b, before_q = np.asarray(rep.behaviors), np.asarray(rep.qualities)
        rep, ins = (_insert_banded if banded else _insert)(rep, actions, jnp.asarray(b), jnp.asarray(q),
                                                          jnp.asarray(ok), jnp.float32(t_dist))
        ref_b, ref_q, status, archived = reference.insert(ref_b, ref_q, b, q, ok, t_dist, capacity)
        n = int(rep.count)
        assert [NAMES[int(s)] for s in ins.status] == status
        np.testing.assert_array_equal(np.asarray(rep.behaviors[:n]), ref_b)
        np.testing.assert_array_equal(np.asarray(rep.qualities[:n]), ref_q)
        assert np.asarray(rep.valid).sum() == n == len(ref_b)
        # The archived skills, in order.
        mask = np.asarray(ins.archived)
        victim_old, victim_cand = np.asarray(ins.victim_slot), np.asarray(ins.victim_candidate)
        got = []
        for i in np.flatnonzero(mask):
            if victim_old[i] >= 0:
                got.append((before_b[victim_old[i]], before_q[victim_old[i]]))
            else:
                j = victim_cand[i] if victim_cand[i] >= 0 else i
                got.append((b[j], q[j]))
        assert len(got) == len(archived)
        for (gb, gq), (rb, rq) in zip(got, archived, strict=True):
            np.testing.assert_array_equal(gb, rb)
            assert gq == rq
        # Novelty and the neighbour lists against brute force.
        np.testing.assert_allclose(np.asarray(rep.novelty[:n]), reference.novelty(ref_b, K), rtol=1e-5, atol=1e-6)
        _check_lists(rep, n)


def test_a_tie_between_two_skills_of_the_same_generation_goes_to_the_lower_slot():
    """Candidate 2 is 0.09375 from candidate 0 (added in slot 1) and from candidate 1 (which replaced slot 0):
    slot 0 is the nearest, whose quality it does not beat. Picking the earlier candidate would replace slot 1."""
    rep = Repertoire.empty(8, 1, 2, K + 2)
    rep, _ = _insert(rep, jnp.zeros((1, 1)), jnp.zeros((1, 2)), jnp.array([0.5]), jnp.array([True]), jnp.float32(0.1))
    b = jnp.array([[0.25, 0.0], [0.0625, 0.0], [0.15625, 0.0]])
    rep, ins = _insert(rep, jnp.zeros((3, 1)), b, jnp.array([0.1, 0.9, 0.5]), jnp.ones(3, bool), jnp.float32(0.1))
    assert [NAMES[int(s)] for s in ins.status] == ["added", "replaced", "rejected"]
    np.testing.assert_array_equal(ins.slot[:2], [1, 0])
    np.testing.assert_array_equal(rep.qualities[:2], np.float32([0.9, 0.1]))


def _check_lists(rep, n):
    """Every listed distance is right and every skill closer than the radius is listed."""
    b = np.asarray(rep.behaviors[:n], np.float64)
    d2 = ((b[:, None] - b[None]) ** 2).sum(-1)
    lists = rep.neighbours
    for i in range(n):
        idx = np.asarray(lists.index[i])
        listed = set(idx[idx >= 0].tolist())
        np.testing.assert_allclose(np.asarray(lists.sq_dist[i])[idx >= 0], d2[i, idx[idx >= 0]], rtol=1e-4,
                                   atol=1e-7)
        closer = {j for j in range(n) if j != i and d2[i, j] < float(lists.radius[i]) * (1 - 1e-5)}
        assert closer <= listed


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 300), k=st.integers(1, 9), ties=st.booleans())
def test_k_smallest_matches_sort(seed, n, k, ties):
    rng = np.random.default_rng(seed)
    v = rng.random((5, n)).astype(np.float32)
    if ties:
        v = np.round(v * 4) / 4
    v[rng.random((5, n)) < 0.2] = np.inf
    vals, idx = jax.jit(neighbours.k_smallest, static_argnums=1)(jnp.asarray(v), k)
    for r in range(5):
        order = sorted(range(n), key=lambda j: (v[r, j], j))[:k]
        want = [v[r, j] for j in order] + [np.inf] * (k - len(order))
        np.testing.assert_array_equal(np.asarray(vals[r]), want)
        want_idx = [j if np.isfinite(v[r, j]) else -1 for j in order] + [-1] * (k - len(order))
        np.testing.assert_array_equal(np.asarray(idx[r]), want_idx)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), capacity=st.sampled_from([6, 40]), spread=st.sampled_from([0.05, 0.2]))
def test_insertion_invariants(seed, capacity, spread):
    """Per candidate, against the repertoire as the previous candidates left it (replayed from the statuses)."""
    pop, t_dist = 12, 0.1
    rep = Repertoire.empty(capacity, 1, 2, K + 2)
    for b, q, ok in _batches(seed, 4, pop, spread):
        before_b, before_q = np.asarray(rep.behaviors).copy(), np.asarray(rep.qualities).copy()
        rep, ins = _insert(rep, jnp.zeros((pop, 1)), b, q, ok, t_dist)
        status, slot = np.asarray(ins.status), np.asarray(ins.slot)
        for i in range(pop):
            if status[i] == AddStatus.REPLACED:
                # Only a candidate within t_dist of the skill it replaces, and only with a higher quality:
                # the quality of a niche never decreases.
                assert np.linalg.norm(before_b[slot[i]] - b[i]) <= t_dist + 1e-6
                assert q[i] > before_q[slot[i]]
            if status[i] in (AddStatus.ADDED, AddStatus.REPLACED):
                before_b[slot[i]], before_q[slot[i]] = b[i], q[i]
        np.testing.assert_array_equal(before_b, rep.behaviors)  # the replay is the repertoire
        assert int(rep.count) == int(np.asarray(rep.valid).sum())
        assert np.all(status[~ok] == AddStatus.SKIPPED)
        # The archive receives every evaluated candidate that was not added, or the skill it replaced.
        assert int(np.asarray(ins.archived).sum()) == ok.sum() - (status == AddStatus.ADDED).sum()


def test_vmapped_insertion_equals_member_by_member():
    """A batch of repertoires of different sizes (different prefixes, full searches in some members only)."""
    pop, capacity, t_dist = 12, 40, jnp.float32(0.1)
    spreads = [0.05, 0.2, 0.05, 0.4]
    gens = [list(_batches(seed, 5, pop, spread)) for seed, spread in enumerate(spreads)]
    singles = [Repertoire.empty(capacity, 1, 2, K + 2) for _ in spreads]
    batch = jax.tree.map(lambda *x: jnp.stack(x), *singles)
    batched = jax.jit(jax.vmap(_insert_fn, in_axes=(0, 0, 0, 0, 0, None)))
    for g in range(5):
        actions = jnp.broadcast_to(jnp.arange(pop, dtype=jnp.float32)[:, None], (len(spreads), pop, 1))
        b, q, ok = (jnp.asarray(np.stack([gens[s][g][i] for s in range(len(spreads))])) for i in range(3))
        batch, ins = batched(batch, actions, b, q, ok, t_dist)
        for s in range(len(spreads)):
            singles[s], want = _insert(singles[s], actions[s], b[s], q[s], ok[s], t_dist)
            got = jax.tree.map(lambda x, s=s: x[s], (batch, ins))
            for name in ("status", "alive", "victim_slot", "victim_candidate"):
                np.testing.assert_array_equal(getattr(got[1], name), getattr(want, name), err_msg=name)
            np.testing.assert_array_equal(repertoire.written_slots(got[1], capacity),
                                          repertoire.written_slots(want, capacity))
            for name in ("actions", "behaviors", "qualities", "valid", "count"):
                np.testing.assert_array_equal(getattr(got[0], name), getattr(singles[s], name), err_msg=name)
            np.testing.assert_array_equal(got[0].neighbours.index, singles[s].neighbours.index)
            np.testing.assert_allclose(got[0].novelty, singles[s].novelty, rtol=1e-6)
    assert len({int(c) for c in batch.count}) > 1  # members really had different sizes


def _random_generations(rng, batch, capacity, pop, dim):
    """`batch` random insertion problems of one shape: repertoires from empty to full, candidates clustered
    around three centres (or not), some duplicated, qualities rounded to make ties, a few skipped."""
    counts = rng.integers(0, capacity + 1, batch)
    counts[:4] = [0, capacity, capacity - 1, capacity - pop // 2]  # empty, full, and filling up in the generation
    old_b = rng.random((batch, capacity, dim)).astype(np.float32)
    centres = rng.random((batch, 3, dim))
    spread = rng.choice([0.002, 0.05, 0.3], (batch, 1, 1))
    around = centres[np.arange(batch)[:, None], rng.integers(0, 3, (batch, pop))]
    b = around + spread * rng.normal(size=(batch, pop, dim))
    b[:, pop // 2:pop // 2 + 4] = b[:, :1]  # exact duplicates
    q = rng.random((batch, pop)).round(rng.choice([1, 6])).astype(np.float32)
    reps = jax.vmap(lambda ob, oq, n: Repertoire.empty(capacity, 1, dim, K + 2).replace(
        behaviors=ob, qualities=oq, valid=jnp.arange(capacity) < n, count=n))(
        jnp.asarray(old_b), jnp.asarray(rng.random((batch, capacity)).astype(np.float32)),
        jnp.asarray(counts, jnp.int32))
    return reps, jnp.asarray(b.astype(np.float32)), jnp.asarray(q), jnp.asarray(rng.random((batch, pop)) > 0.1)


@pytest.mark.parametrize(("dim", "window"), [(1, 16), (3, 1), (8, 16)])
def test_the_parallel_rule_is_the_sequential_rule_bit_for_bit(dim, window, monkeypatch):
    """The sequential rule, kept as the oracle, against the rounds, on 96 random problems per dimension (vmapped):
    statuses, slots of the skills written, replaced skills and candidates, who is alive; rounds <= P + 1. The
    rounds read each candidate's runs of grid cells, `window` * 4^j places (or P) of each; the full searches of
    the skills that remain run 3 candidates at a time."""
    monkeypatch.setattr(insertion, "MIN_RUN", window)
    monkeypatch.setattr(insertion, "SEARCH_ROWS", 3)
    capacity, pop = 48, 24

    def both(rep, b, q, usable, t_dist):
        near_d, near_i = bands.nearest_before(2, capacity, rep, b)
        return (oracle.sequential_rule(rep, b, near_d, near_i, neighbours.sq_dists(b, b), q, usable, t_dist),
                insertion.parallel_rule(rep, b, near_d, near_i, q, usable, t_dist,
                                          bands.searched(b, usable, t_dist)[0]))

    rng = np.random.default_rng(dim)
    reps, b, q, usable = _random_generations(rng, 96, capacity, pop, dim)
    t_dist = jnp.asarray(rng.choice([0.01, 0.1, 0.4], 96), jnp.float32)
    seq, par = jax.jit(jax.vmap(both))(reps, b, q, usable, t_dist)
    for name in ("status", "alive", "victim_slot", "victim_candidate"):
        np.testing.assert_array_equal(getattr(par, name), getattr(seq, name), err_msg=name)
    np.testing.assert_array_equal(np.where(par.alive, par.slot, -1), np.where(seq.alive, seq.slot, -1))
    statuses = set(np.unique(seq.status).tolist())
    assert statuses == set(range(5)), statuses  # every outcome occurred, DROPPED_FULL included
    assert (np.asarray(par.rounds) <= pop + 1).all() and np.asarray(par.rounds).max() > 3


def test_candidates_that_cannot_touch_each_other_settle_in_three_rounds():
    """64 far apart candidates in an empty repertoire: round 1 decides them, round 2 their slots (the count of
    added skills before each), round 3 finds nothing changed."""
    pop = 64
    rep = Repertoire.empty(128, 1, 2, K + 2)
    b = jnp.stack([jnp.arange(pop) * 0.5, jnp.zeros(pop)], axis=1)
    _, ins = _insert(rep, jnp.zeros((pop, 1)), b, jnp.ones(pop), jnp.ones(pop, bool), jnp.float32(0.1))
    assert int(ins.rounds) == 3 and (np.asarray(ins.slot) == np.arange(pop)).all()


def test_a_minimum_that_matches_no_entry_is_found_again_in_one_reduction():
    """XLA may fuse a distance matrix into both the minimum and the match with it, rounding one copy otherwise: the
    minimum then matches no entry (seen under jit: an id of int32 max). Such a row is searched again whole."""
    values = jnp.array([[0.5, 0.25, 0.25, 1.0], [2.0, 3.0, 1.0, jnp.inf]])
    ids = jnp.broadcast_to(jnp.arange(4), values.shape)
    big = jnp.iinfo(jnp.int32).max
    m, sel = neighbours._matched(values, ids, jnp.array([0.2500001, 1.0]), jnp.array([big, 2]))
    np.testing.assert_array_equal(m, [0.25, 1.0])  # the first row's own minimum, the second row's as it was
    np.testing.assert_array_equal(sel, [1, 2])  # ties: the smaller id
    assert neighbours.min_with_index(jnp.array([[jnp.nan, jnp.nan]]), jnp.arange(2)[None])[1][0] == big


@pytest.mark.parametrize("dim", [1, 2, 8])
def test_a_band_holds_every_row_within_t_dist_and_the_axis_is_the_narrowest(dim):
    """Brute force: every row within t_dist of a query (distances as `sq_dists` rounds them) lies in its band, on
    points far from the origin (rounding) with coordinates exactly t_dist apart, and the chosen axis is the one
    whose widest band is narrowest where one axis is clearly so."""
    rng = np.random.default_rng(dim)
    t_dist = 0.125
    lattice = 1000.0 + t_dist * rng.integers(0, 6, (300, dim))
    points = (lattice + rng.choice([0.0, 1e-4], lattice.shape)).astype(np.float32)
    ok = rng.random(300) > 0.1
    rows = jnp.asarray(points)
    axis = compiled(bands.axis)(rows, jnp.asarray(ok), jnp.float32(t_dist))
    order, lo, hi, widest = compiled(bands.bands)(rows[:50], jnp.asarray(ok[:50]), rows, jnp.asarray(ok), axis,
                                              jnp.float32(t_dist))
    d = np.asarray(neighbours.sq_dists(rows[:50], rows))
    for i in np.flatnonzero(ok[:50]):
        band = set(np.asarray(order)[int(lo[i]):int(hi[i])].tolist())
        assert set(np.flatnonzero(ok & (d[i] <= np.float32(t_dist) ** 2)).tolist()) <= band
        assert int(hi[i]) - int(lo[i]) <= int(widest)
    if dim > 1:  # spread one axis 40 times wider: its bands are the narrowest
        spread = rows.at[:, dim - 1].multiply(40.0)
        assert int(bands.axis(spread, jnp.asarray(ok), jnp.float32(t_dist))) == dim - 1
