"""The parts of this library's M-QD: the ensemble, anchored predictions, batch-diverse acquisition, the fallback
and the model's metrics, each against a hand-computed case or a brute-force reference."""

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from compiled import compiled

from mqd_jax import Anchoring, Config, IsoLine, ModelEmitter, Params, Steering, run_mqd
from mqd_jax.core import algorithms
from mqd_jax.core import repertoire as repertoire_lib
from mqd_jax.core.emitter import Evaluated
from mqd_jax.core.repertoire import AddStatus, Repertoire
from mqd_jax.emitters import diverse
from mqd_jax.emitters.acquisition import Budgeted, Judged, Threshold
from mqd_jax.emitters.diverse import Diverse, parent_factor
from mqd_jax.emitters.model_emitter import ModelEmitterState, _share, opener_auc
from mqd_jax.emitters.pursuit import Fallback, FallbackState
from mqd_jax.experiment.migrations import config_from
from mqd_jax.surrogate import model
from mqd_jax.surrogate.gate import Gate
from mqd_jax.surrogate.surrogate import Surrogate, SurrogateState

greedy_diverse, rounds_diverse = compiled(diverse.greedy_diverse), compiled(diverse.rounds_diverse)
pool_neighbours = compiled(diverse.pool_neighbours)


def select(rule, *args):
    """`rule.select(*args)`, compiled."""
    return compiled(rule.select)(*args)


def judge(emitter, *args, **kwargs):
    """`emitter.judge(*args, **kwargs)`, compiled."""
    return compiled(emitter.judge)(*args, **kwargs)


def repertoire_of(behaviors, qualities, actions=None, capacity=8):
    b = np.asarray(behaviors, np.float32)
    n = len(b)
    a = np.zeros((n, 3), np.float32) if actions is None else np.asarray(actions, np.float32)
    rep = Repertoire.empty(capacity, a.shape[1], b.shape[1], 4)
    return rep.replace(actions=rep.actions.at[:n].set(a), behaviors=rep.behaviors.at[:n].set(b),
                       qualities=rep.qualities.at[:n].set(qualities), valid=jnp.arange(capacity) < n,
                       count=jnp.int32(n))


def judged(behaviors, qualities, rep, spread=None, k=5, validity=None):
    """A Judged pool whose distances to the nearest skill and to the k nearest are computed by brute force."""
    b = np.asarray(behaviors, np.float32)
    n = b.shape[0]
    skills = np.asarray(rep.behaviors[:int(rep.count)])
    d = np.sqrt(((b[:, None] - skills[None]) ** 2).sum(-1))
    near = np.pad(np.sort(d, axis=1), ((0, 0), (0, max(k - d.shape[1], 0))), constant_values=np.inf)[:, :k]
    return Judged(jnp.asarray(b), jnp.asarray(qualities, jnp.float32), jnp.zeros(n) if spread is None else
                  jnp.asarray(spread), jnp.asarray(d.min(1)), jnp.asarray(rep.qualities)[d.argmin(1)], jnp.zeros(n),
                  jnp.zeros(n), jnp.asarray(near), None if validity is None else jnp.asarray(validity, jnp.float32))


def greedy_reference(b, q, spread, skills, skill_qualities, wanted, t_dist, beta, num, neighbours, plausible=None,
                     parent_novelty=None, quality_share=0.0, quality_margin=0.0):
    """greedy_diverse written out: each step scores every free candidate against the repertoire's skills and the
    wanted candidates chosen so far; a predicted opener's distance times its parent's novelty over the pool's
    mean (1 without a parent); with m = round(quality_share * num), the steps ceil(j * num / m) - 1 for j = 1..m
    prefer non-openers that beat their nearest skill's quality by more than quality_margin."""
    plausible = np.ones(len(b), bool) if plausible is None else plausible
    factor = np.ones(len(b)) if parent_novelty is None else np.where(
        np.isnan(parent_novelty), 1.0, parent_novelty / np.nanmean(parent_novelty))
    imagined_b, imagined_q = list(skills), list(skill_qualities)
    free, rows = np.ones(len(b), bool), []
    m = round(quality_share * num)
    quality_steps = {-(-j * num // m) - 1 for j in range(1, m + 1)}
    for step in range(num):
        best = None
        for i in np.flatnonzero(free):
            d = np.linalg.norm(np.asarray(imagined_b) - b[i], axis=1)
            near = np.sort(d)[:neighbours]
            opens = near[0] + beta * spread[i] > t_dist
            improvement = q[i] - imagined_q[int(np.argmin(d))]
            value = (near.mean() + beta * spread[i]) * factor[i] if opens else improvement
            preferred = (not opens and improvement > quality_margin) if step in quality_steps else opens
            rank = (bool(wanted[i]), bool(preferred), bool(plausible[i]), value)
            if best is None or rank > best[0]:
                best = (rank, i)
        pick = best[1]
        rows.append(pick)
        free[pick] = False
        if wanted[pick]:
            imagined_b.append(b[pick])
            imagined_q.append(q[pick])
    return rows


@pytest.mark.parametrize("neighbours, skills, judge_validity, parents, quality_share, quality_margin", [
    (1, 6, False, False, 0.0, 0.0), (3, 6, False, False, 0.0, 0.0), (3, 2, False, False, 0.0, 0.0),
    (1, 6, True, False, 0.0, 0.0), (1, 6, False, True, 0.0, 0.0), (3, 6, True, True, 0.0, 0.0),
    (1, 6, False, False, 0.3, 0.0), (3, 16, True, True, 0.5, 0.0), (1, 16, False, False, 0.5, 0.2)])
def test_greedy_diverse_matches_a_reference(neighbours, skills, judge_validity, parents, quality_share,
                                            quality_margin):
    """Random pools: the scan's choice equals the rule written out, for the nearest distance and for the mean of
    the 3 nearest (also with fewer skills than that: the mean over those there are), with a validity
    judgement (likely unusable candidates after the others of their tier), with the parents' novelty
    (parent_weight 1; some candidates without a parent) and with quality steps (with and without a margin)."""
    key = jax.random.split(jax.random.PRNGKey(neighbours + skills), 4)
    rep = repertoire_of(np.asarray(jax.random.uniform(key[0], (skills, 2))),
                        np.asarray(jax.random.uniform(key[1], (skills,))), capacity=16)
    b = np.asarray(jax.random.uniform(key[2], (30, 2)))
    q = np.asarray(jax.random.uniform(key[3], (30,)))
    spread = np.linspace(0.0, 0.05, 30).astype(np.float32)
    wanted = np.arange(30) % 4 != 0
    validity = np.asarray(jax.random.uniform(jax.random.PRNGKey(7), (30,))) if judge_validity else None
    pool = judged(b, q, rep, spread, k=5, validity=validity)
    parent_novelty = None
    if parents:
        parent_novelty = np.array(jax.random.uniform(jax.random.PRNGKey(8), (30,)), np.float32)
        parent_novelty[::7] = np.nan
        pool = pool.replace(parent_novelty=jnp.asarray(parent_novelty))
    rows = greedy_diverse(pool, jnp.asarray(wanted), jnp.float32(0.1), 0.5, 12, neighbours, float(parents),
                          quality_share, jnp.float32(quality_margin))
    expected = greedy_reference(b, q, spread, np.asarray(rep.behaviors[:skills]), np.asarray(rep.qualities[:skills]),
                                wanted, 0.1, 0.5, 12, neighbours, None if validity is None else validity >= 0.5,
                                parent_novelty, quality_share, quality_margin)
    np.testing.assert_array_equal(rows, expected)
    if parents:  # weight 0: the parents' novelty is not read
        np.testing.assert_array_equal(greedy_diverse(pool, jnp.asarray(wanted), jnp.float32(0.1), 0.5, 12, neighbours),
                                      greedy_diverse(pool.replace(parent_novelty=None), jnp.asarray(wanted),
                                                     jnp.float32(0.1), 0.5, 12, neighbours))


def test_greedy_diverse_by_parent_novelty_by_hand():
    """Two predicted openers: 0 a little farther from the skill, 1 the child of a parent three times as novel.
    By distance 0 goes first; weighted by the parent's novelty 1 (0.3 * 1.5 > 0.31 * 0.5); with the parents'
    novelty squared the ratio grows; without a parent a candidate keeps its distance."""
    rep = repertoire_of([[0.0, 0.0]], [0.5])
    pool = judged([[0.31, 0.0], [0.0, 0.3]], [0.5, 0.5], rep).replace(parent_novelty=jnp.array([0.1, 0.3]))
    wanted = jnp.ones(2, bool)
    np.testing.assert_array_equal(greedy_diverse(pool, wanted, jnp.float32(0.05), 0.0, 2), [0, 1])
    np.testing.assert_array_equal(greedy_diverse(pool, wanted, jnp.float32(0.05), 0.0, 2, parent_weight=1.0), [1, 0])
    np.testing.assert_allclose(parent_factor(pool, 2.0), [0.25, 2.25], rtol=1e-6)
    no_parent = pool.replace(parent_novelty=jnp.array([jnp.nan, 0.3]))  # 0 keeps 0.31, 1 gets 0.3 * 1
    np.testing.assert_array_equal(greedy_diverse(no_parent, wanted, jnp.float32(0.05), 0.0, 2, parent_weight=1.0),
                                  [0, 1])
    np.testing.assert_allclose(parent_factor(pool.replace(parent_novelty=jnp.zeros(2)), 1.0), [1.0, 1.0])


def test_diverse_cap_by_hand():
    """Two predicted openers, 0 at 10 t_dist from the skill with a parent a third as novel as 1's, 1 at 2 t_dist, and
    a non-opener with the most novel parent. Uncapped 0 goes first (0.5 x 0.214 > 0.1 x 0.643); with the distance
    counted up to 1 t_dist, 1 (its parent's novelty decides; in rounds); up to 3 t_dist, 1 too (its distance under the
    cap: 0.1 x 0.643 > 0.15 x 0.214; `Diverse`, greedy); the non-opener stays last."""
    rep = repertoire_of([[0.0, 0.0]], [0.5])
    pool = judged([[0.5, 0.0], [0.0, 0.1], [0.04, 0.0]], [0.5] * 3, rep).replace(
        parent_novelty=jnp.array([0.1, 0.3, 1.0]))
    wanted, t = jnp.ones(3, bool), jnp.float32(0.05)
    np.testing.assert_array_equal(greedy_diverse(pool, wanted, t, 0.0, 3, parent_weight=1.0), [0, 1, 2])
    np.testing.assert_array_equal(rounds_diverse(pool, wanted, t, 0.0, 3, 4, parent_weight=1.0, cap=1.0), [1, 0, 2])
    rows, _, _ = select(Diverse(1, 0.0, parent_weight=1.0, cap=3.0), jax.random.PRNGKey(0), (), pool, rep, wanted,
                                                                    Config().params().replace(t_dist=t), 3)
    np.testing.assert_array_equal(rows, [1, 0, 2])


def test_greedy_diverse_by_novelty_by_hand():
    """Candidate 0 is a little farther from its nearest skill, candidate 1 in emptier surroundings: 0 goes first
    ranked by the nearest distance, 1 ranked by the mean distance to the 2 nearest."""
    rep = repertoire_of([[0.0, 0.0], [0.0, 0.1], [1.0, 0.0], [1.0, 0.9]], [0.5] * 4)
    pool = judged([[0.31, 0.0], [0.7, 0.0]], [0.5, 0.5], rep)  # nearest 0.31 / 0.3; second nearest 0.326 / 0.7
    wanted = jnp.ones(2, bool)
    np.testing.assert_array_equal(greedy_diverse(pool, wanted, jnp.float32(0.05), 0.0, 2, 2), [1, 0])
    np.testing.assert_array_equal(greedy_diverse(pool, wanted, jnp.float32(0.05), 0.0, 2, 1), [0, 1])
    with pytest.raises(ValueError, match=r"Diverse\.neighbours=6 needs"):
        select(Diverse(1, neighbours=6), jax.random.PRNGKey(0), (), pool, rep, wanted, Config().params(), 2)


def test_ensemble_members_train_as_independent_networks(linear_task):
    """An ensemble of 3 trained together equals each member trained alone on its own mini-batches."""
    actions = jax.random.uniform(jax.random.PRNGKey(1), (64, 3), minval=-1.0, maxval=1.0)
    b, q, _ = linear_task.evaluate(actions, None)
    rep = repertoire_of(b, q, actions, capacity=64)
    ensemble = compiled(model.init)(jax.random.PRNGKey(0), 8, linear_task, ensemble_size=3)
    key = jax.random.PRNGKey(2)
    trained, _ = compiled(model.train)(ensemble, key, rep, linear_task, jnp.float32(0.01), 4, 5)
    rows = jax.random.randint(key, (5, 3, 4), 0, 64)
    net = model.network(8, linear_task)
    x, y = model.normalize_actions(actions, linear_task), model.normalize_targets(b, q, linear_task)
    adam = optax.adam(0.01)
    for e in range(3):
        params = jax.tree.map(lambda v: v[e], ensemble.params)  # noqa: B023
        state = adam.init(params)
        for step in range(5):
            idx = rows[step, e]
            grads = jax.grad(lambda p: ((net.apply(p, x[idx]) - y[idx]) ** 2).mean())(params)  # noqa: B023
            updates, state = adam.update(grads, state, params)
            params = optax.apply_updates(params, updates)
        for got, want in zip(jax.tree.leaves(jax.tree.map(lambda v: v[e], trained.params)),  # noqa: B023
                             jax.tree.leaves(params), strict=True):
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    # The ensemble's prediction is the members' mean.
    members = compiled(model.predict_members)(trained, actions[:5], linear_task)
    mean_b, mean_q = compiled(model.predict)(trained, actions[:5], linear_task)
    np.testing.assert_allclose(mean_b, members[..., :-1].mean(0), rtol=1e-6)
    np.testing.assert_allclose(mean_q, members[:, :, -1].mean(0), rtol=1e-6)


@dataclasses.dataclass(frozen=True)
class _Known(Surrogate):
    """Members with known predictions: member e says (a0 + e, a1 - e, a2) for action a."""

    def members(self, state, actions, task, inputs=None):
        shift = jnp.arange(2.0)[:, None, None] * jnp.array([1.0, -1.0, 0.0])
        return actions[None] + shift


def knowing(acquisition, k, **anchoring):
    """A model emitter whose surrogate is `_Known()`, anchored as `anchoring` says."""
    return ModelEmitter(IsoLine(), acquisition, _Known(), k=k, **anchoring)


def anchored(emitter, **changes):
    """`emitter` with its anchoring settings changed."""
    return dataclasses.replace(emitter, **changes)


NO_STATE = ModelEmitterState(surrogate=SurrogateState(model=None), inner=(), evaluations=jnp.int32(0),
                             parts={"anchoring": ()})


def test_anchored_predictions_and_the_spread_by_brute_force(linear_task):
    rep = repertoire_of([[0.2, 0.3], [0.7, 0.9]], [0.4, 0.6], actions=[[0.0, 0.0, 0.0], [0.5, 0.5, 0.5]])
    pool = jnp.array([[0.1, 0.0, -0.1], [0.6, 0.4, 0.5], [-0.9, 0.9, 0.9]])
    emitter = knowing(Diverse(), 1, parts=(Anchoring("always", "nearest"),))
    got = judge(emitter, NO_STATE, pool, rep, linear_task)
    for i, a in enumerate(np.asarray(pool)):
        j = int(np.argmin([np.sum((a - r) ** 2) for r in np.asarray(rep.actions[:2])]))  # action box [-1, 1]: x1
        members = [np.array([a[0] + e, a[1] - e, a[2]]) - np.array([rep.actions[j, 0] + e, rep.actions[j, 1] - e,
                                                                   rep.actions[j, 2]]) for e in range(2)]
        known = np.array([*rep.behaviors[j], rep.qualities[j]])
        mean = np.mean([known + m for m in members], axis=0)
        np.testing.assert_allclose(got.behaviors[i], mean[:2], rtol=1e-6)
        np.testing.assert_allclose(got.qualities[i], mean[2], rtol=1e-6)
    # Anchored differences cancel the members' offsets: they agree (spread 0); not anchored they disagree by 1/2
    # on each behavior axis around the mean.
    np.testing.assert_allclose(got.spread, 0.0, atol=1e-6)
    plain = judge(anchored(emitter, parts=()), NO_STATE, pool, rep, linear_task)
    np.testing.assert_allclose(plain.behaviors, np.asarray(pool)[:, :2] + [0.5, -0.5], rtol=1e-6)
    np.testing.assert_allclose(plain.spread, 0.5, rtol=1e-6)
    # An empty repertoire has nothing to anchor at: the plain prediction.
    empty = judge(emitter, NO_STATE, pool, Repertoire.empty(8, 3, 2, 4), linear_task)
    np.testing.assert_allclose(empty.behaviors, plain.behaviors)


def test_judged_nearest_skill_neighbours_and_the_proposals_distances_by_brute_force(linear_task):
    """The nearest skill (distance, quality; ties to the lower slot) and the K nearest come from two searches: both
    as a brute-force search gives them, and a proposal's predicted distances are its kept rows' distances."""
    rep = repertoire_of([[0.5, 0.0], [0.75, 0.0], [0.25, 0.0], [0.5, 0.5]], [0.1, 0.2, 0.3, 0.4])
    # Plain predictions = the actions' first two coordinates + (0.5, -0.5) on average over the two members; all
    # binary fractions, so that the first two rows' ties (slots 0 and 1; 0 and 3) are exact.
    pool = jnp.array([[0.125, 0.5, 0.0], [0.0, 0.75, 0.0], [-0.375, 1.0, 0.0], [0.25, -0.25, 0.0],
                      [-0.5, 0.25, 0.0]])
    emitter = knowing(Diverse(2), 3)
    got = judge(emitter, NO_STATE, pool, rep, linear_task)
    b = np.asarray(pool)[:, :2] + [0.5, -0.5]
    d = np.sqrt(((b[:, None] - np.asarray(rep.behaviors[:4])[None]) ** 2).sum(-1))
    nearest = d.argmin(1)  # the first of equal minima: the lower slot
    assert d[0, 0] == d[0, 1] and d[1, 0] == d[1, 3] and nearest[0] == nearest[1] == 0
    np.testing.assert_allclose(got.distance, d.min(1), rtol=1e-6)
    np.testing.assert_allclose(got.nearest_quality, np.asarray(rep.qualities)[nearest], rtol=1e-6)
    np.testing.assert_allclose(got.neighbours, np.sort(d, 1)[:, :3], rtol=1e-6)
    np.testing.assert_allclose(got.novelty, np.sort(d, 1)[:, :3].mean(1), rtol=1e-6)
    state = compiled(emitter.init)(jax.random.PRNGKey(0), linear_task, 64)
    state = state.replace(evaluations=jnp.int32(emitter.warmup_samples))  # past warm-up: the rule chooses
    proposal = compiled(emitter.propose)(jax.random.PRNGKey(1), state, rep, linear_task,
                               Params(jnp.float32(0.02), emitter.default_params()), 3)
    kept = np.sqrt(((np.asarray(proposal.info.predicted_behaviors)[:, None] - np.asarray(rep.behaviors[:4])[None])
                    ** 2).sum(-1)).min(1)
    np.testing.assert_allclose(proposal.info.predicted_distance, kept, rtol=1e-6)
    empty = judge(emitter, NO_STATE, pool, Repertoire.empty(8, 3, 2, 4), linear_task)
    assert np.all(np.isinf(empty.distance)) and np.all(np.asarray(empty.nearest_quality) == 0.0)


def test_predictions_anchored_at_the_named_parents_by_hand(linear_task):
    rep = repertoire_of([[0.2, 0.3], [0.7, 0.9]], [0.4, 0.6], actions=[[0.0, 0.0, 0.0], [0.5, 0.5, 0.5]])
    pool = jnp.array([[0.1, 0.0, -0.1], [0.6, 0.4, 0.5], [-0.9, 0.9, 0.9]])
    emitter = knowing(Diverse(), 1, parts=(Anchoring("always"),))
    assert emitter.part("anchoring").anchor == "parent"
    # Row 0's parent is the skill farther from it in action space (slot 1), row 1's slot 0; row 2 has none.
    got = judge(emitter, NO_STATE, pool, rep, linear_task, parents=jnp.array([1, 0, -1]))
    for i, j in ((0, 1), (1, 0)):
        a, p = np.asarray(pool[i]), np.asarray(rep.actions[j])
        # The members' offsets cancel: b(parent) + (a - parent) on the behavior axes, q(parent) + a2 - p2.
        np.testing.assert_allclose(got.behaviors[i], np.asarray(rep.behaviors[j]) + (a - p)[:2], rtol=1e-6)
        np.testing.assert_allclose(got.qualities[i], float(rep.qualities[j]) + a[2] - p[2], rtol=1e-6)
    plain = judge(anchored(emitter, parts=()), NO_STATE, pool, rep, linear_task)
    np.testing.assert_allclose(got.behaviors[2], plain.behaviors[2])  # no parent: the plain prediction
    # The parents' novelty, as the repertoire holds it; NaN without a parent, None where no parents are named.
    novel = rep.replace(novelty=rep.novelty.at[:2].set(jnp.array([0.25, 0.75])))
    np.testing.assert_array_equal(judge(emitter, NO_STATE, pool, novel, linear_task, parents=jnp.array([1, 0, -1]))
                                  .parent_novelty, [0.75, 0.25, np.nan])
    assert judge(emitter, NO_STATE, pool, novel, linear_task).parent_novelty is None
    # An inner emitter that names no parents: anchored at the nearest skill, as anchor="nearest".
    nearest = judge(anchored(emitter, parts=(Anchoring("always", "nearest"),)), NO_STATE, pool, rep, linear_task)
    np.testing.assert_allclose(judge(emitter, NO_STATE, pool, rep, linear_task).behaviors, nearest.behaviors)
    assert not np.allclose(got.behaviors[:2], nearest.behaviors[:2])
    with pytest.raises(ValueError, match=r"Anchoring\.mode='nearest' is invalid"):
        Anchoring("nearest")
    with pytest.raises(ValueError, match=r"Anchoring\.anchor="):
        Anchoring(anchor="first")


def test_greedy_diverse_by_hand():
    rep = repertoire_of([[0.0, 0.0]], [0.5])
    # 0 and 1 are near-duplicates far from the skill; 2 is farther in another direction but less far than 0;
    # 3 sits on the skill with a better quality; 4 on it with a worse one.
    pool = judged([[1.0, 0.0], [0.99, 0.01], [0.0, 0.8], [0.0, 0.0], [0.0, 0.001]], [0.1, 0.1, 0.1, 0.9, 0.2], rep)
    wanted = jnp.ones(5, bool)
    rows = greedy_diverse(pool, wanted, jnp.float32(0.05), 0.0, 5)
    # 0 opens the farthest niche; then 1 is within 0.05 of 0's imagined skill, so 2 goes first; then the rest by
    # predicted improvement over the nearest imagined or real skill: 3 (+0.4 over the skill), 1 (0.0 over 0's
    # imagined skill), 4 (-0.3).
    np.testing.assert_array_equal(rows, [0, 2, 3, 1, 4])
    # Three quality steps of five, the second, fourth and fifth: the second takes the improver 3 before the opener
    # 2; the fourth finds no improver left (1 only equals 0's imagined quality, 4 is below the skill's) and takes
    # the best of the rest.
    np.testing.assert_array_equal(greedy_diverse(pool, wanted, jnp.float32(0.05), 0.0, 5, quality_share=0.6),
                                  [0, 3, 2, 1, 4])
    # All quality steps: the improver first, then the openers (farthest first), then the rest.
    np.testing.assert_array_equal(greedy_diverse(pool, wanted, jnp.float32(0.05), 0.0, 5, quality_share=1.0),
                                  [3, 0, 2, 1, 4])
    # Budgeted ranking has no imagined skills: both duplicates before 2.
    ranked = select(Budgeted(1), jax.random.PRNGKey(0), (),
                                pool.replace(novelty=jnp.array([1.0, 0.99, 0.8, 0.0, 0.001]),
                                             improvement=jnp.array([-0.4, -0.4, -0.4, 0.4, -0.3])),
                                rep, wanted, Params(jnp.float32(0.02), Budgeted(1, t_nov=0.05).default_params()), 5)[0]
    np.testing.assert_array_equal(ranked[:3], [0, 1, 2])
    # Optimism: a spread of 0.2 lifts 4 (0.001 from the skill) above t_dist, ahead of the improvers.
    rows = greedy_diverse(pool.replace(spread=jnp.array([0, 0, 0, 0, 0.2])), wanted, jnp.float32(0.05), 1.0, 5)
    np.testing.assert_array_equal(rows, [0, 2, 4, 3, 1])
    # Wanted candidates first; unwanted ones do not enter the imagined repertoire.
    rows = greedy_diverse(pool, jnp.array([False, True, True, True, True]), jnp.float32(0.05), 0.0, 5)
    np.testing.assert_array_equal(rows, [1, 2, 3, 4, 0])
    # NaN predictions come last (even with a high predicted quality).
    nan = pool.replace(behaviors=pool.behaviors.at[0].set(jnp.nan), qualities=pool.qualities.at[0].set(0.95),
                       distance=pool.distance.at[0].set(jnp.nan))
    assert int(greedy_diverse(nan, wanted, jnp.float32(0.05), 0.0, 5)[-1]) == 0


def test_diverse_selects_num_distinct_rows():
    rep = repertoire_of([[0.5, 0.5]], [0.5])
    pool = judged(jax.random.uniform(jax.random.PRNGKey(0), (40, 2)), jax.random.uniform(jax.random.PRNGKey(1), (40,)),
                  rep)
    params = Config().params()
    rows, rollout, discarded = select(Diverse(4), jax.random.PRNGKey(0), (), pool, rep, jnp.ones(40, bool), params, 10)
    assert len(set(np.asarray(rows).tolist())) == 10 and bool(rollout.all()) and int(discarded) == 30


def opened(b, rows, skills, t_dist):
    """How many of the rows, in order, open a niche: their behavior farther than t_dist from every skill and every
    row before them (brute force)."""
    held, count = list(skills), 0
    for x in np.asarray(b)[np.asarray(rows)]:
        count += not held or np.min(np.linalg.norm(np.asarray(held) - x, axis=1)) > t_dist
        held.append(x)
    return count


@pytest.mark.parametrize("dim", [1, 2, 5])
def test_pool_neighbours_find_every_pair_within_t_dist(dim):
    b = jax.random.uniform(jax.random.PRNGKey(dim), (400, dim)) * (4.0 if dim == 1 else 1.0)  # <= 32 per run
    ok = jnp.arange(400) != 7  # one point left out: in no one's list, with no list
    others, seen = map(np.asarray, pool_neighbours(b, ok, jnp.float32(0.05)))
    d = np.linalg.norm(np.asarray(b)[:, None] - np.asarray(b)[None], axis=-1)
    found = np.zeros_like(d, bool)
    for i in range(400):
        found[i, others[i][seen[i]]] = True
    within = (d <= 0.05) & ~np.eye(400, dtype=bool) & np.asarray(ok)[:, None] & np.asarray(ok)[None]
    assert not (within & ~found).any()  # no run holds more than WINDOW here: exact
    assert not found[7].any() and not found[:, 7].any() and not found[np.eye(400, dtype=bool)].any()


def test_rounds_take_what_greedy_takes_where_no_two_candidates_interact():
    # 60 candidates on a grid 0.1 apart, each 0.025-0.045 from a skill of its own (t_dist 0.02): each opens a niche,
    # none is within t_dist of another, and no choice becomes another's nearest imagined skill, so both choose the
    # best 20 by value, in the same order.
    b = np.stack(np.meshgrid(np.arange(10) / 10, np.arange(6) / 10), -1).reshape(-1, 2)
    gap = np.linspace(0.025, 0.045, 60)[np.random.default_rng(0).permutation(60)]
    rep = repertoire_of(b + np.stack([gap, np.zeros(60)], -1), np.full(60, 0.5), capacity=64)
    pool = judged(b, jnp.full(60, 0.5), rep)
    wanted, t = jnp.ones(60, bool), jnp.float32(0.02)
    greedy = greedy_diverse(pool, wanted, t, 1.0, 20)
    np.testing.assert_array_equal(rounds_diverse(pool, wanted, t, 1.0, 20, 4), greedy)
    np.testing.assert_array_equal(np.sort(np.asarray(greedy)), np.sort(np.argsort(-gap)[:20]))


@pytest.mark.parametrize("crowd", [1.0, 0.3])
def test_rounds_open_nearly_as_many_niches_as_the_greedy_oracle(crowd):
    """The oracle of what diverse means: the greedy choice one at a time. Over 4 pools, spread out and crowded,
    the rounds' choice opens on average at least 95% of the niches it opens and never under 90% (brute force),
    every row distinct. (Crowded pools need more than 8 rounds: with 8, one of these pools opened 71%.)"""
    shares = []
    for seed in range(4):
        key = jax.random.split(jax.random.PRNGKey(seed), 3)
        skills = np.asarray(jax.random.uniform(key[0], (40, 2)))
        b = np.asarray(jax.random.uniform(key[1], (2000, 2))) * crowd
        rep = repertoire_of(skills, np.full(40, 0.5), capacity=64)
        pool = judged(b, jax.random.uniform(key[2], (2000,)), rep)
        wanted, t = jnp.ones(2000, bool), jnp.float32(0.02)
        greedy = greedy_diverse(pool, wanted, t, 1.0, 250, quality_share=0.1)
        rounds = rounds_diverse(pool, wanted, t, 1.0, 250, Diverse().rounds, quality_share=0.1)
        assert len(set(np.asarray(rounds).tolist())) == 250 and int(rounds.min()) >= 0 and int(rounds.max()) < 2000
        shares.append(opened(b, rounds, skills, 0.02) / opened(b, greedy, skills, 0.02))
    assert np.mean(shares) >= 0.95 and min(shares) >= 0.9, shares


def test_rounds_put_unwanted_candidates_last_and_nan_predictions_last_of_the_wanted():
    rep = repertoire_of([[0.5, 0.5]], [0.5])
    b = np.array(jax.random.uniform(jax.random.PRNGKey(4), (50, 2)))
    b[[3, 17]] = np.nan
    pool = judged(b, jax.random.uniform(jax.random.PRNGKey(5), (50,)), rep)
    wanted = jnp.arange(50) % 10 != 0  # 0, 10, ..., 40: not wanted
    for rows in (rounds_diverse(pool, wanted, jnp.float32(0.05), 1.0, 50, 4),
                 greedy_diverse(pool, wanted, jnp.float32(0.05), 1.0, 50)):  # as the oracle does
        rows = np.asarray(rows)
        assert sorted(rows.tolist()) == list(range(50))
        assert set(rows[-5:].tolist()) == {0, 10, 20, 30, 40} and set(rows[-7:-5].tolist()) == {3, 17}


def test_diverse_chooses_in_rounds_from_rounds_from_rows_and_one_at_a_time_below(monkeypatch):
    rep = repertoire_of([[0.5, 0.5]], [0.5])
    pool = judged(jax.random.uniform(jax.random.PRNGKey(0), (40, 2)), jax.random.uniform(jax.random.PRNGKey(1), (40,)),
                  rep)
    args = (jax.random.PRNGKey(0), (), pool, rep, jnp.ones(40, bool), Config().params(), 10)
    greedy = select(Diverse(4, selection="greedy"), *args)[0]
    np.testing.assert_array_equal(select(Diverse(4), *args)[0], greedy)  # "auto" below ROUNDS_FROM: bit for bit
    monkeypatch.setattr(diverse, "ROUNDS_FROM", 10)
    np.testing.assert_array_equal(select(Diverse(4), *args)[0], select(Diverse(4, selection="rounds"), *args)[0])


def test_diverse_quality_margin_is_in_standard_deviations_of_the_repertoire_qualities():
    # Skills of quality 0.2 and 0.6 (standard deviation 0.2; an empty slot of quality 5 is not counted). Candidates
    # 0 and 1 sit on the first skill, predicted 0.05 and 0.3 better; 2 opens a niche far away.
    rep = repertoire_of([[0.0, 0.0], [1.0, 0.0]], [0.2, 0.6])
    rep = rep.replace(qualities=rep.qualities.at[5].set(5.0))
    pool = judged([[0.0, 0.0], [0.0, 0.001], [0.0, 1.0]], [0.25, 0.5, 0.0], rep)
    params, wanted, key = Config().params().replace(t_dist=jnp.float32(0.05)), jnp.ones(3, bool), jax.random.PRNGKey(0)
    # One quality step of one: both beat the skill by more than 0.5 x 0.2 = 0.1? Only 1 (by 0.3); it goes first.
    rows, _, _ = select(Diverse(1, 0.0, quality_share=1.0, quality_margin=0.5), key, (), pool, rep, wanted, params, 3)
    np.testing.assert_array_equal(rows, [1, 2, 0])
    # A margin of 2 x 0.2 = 0.4 leaves no improver preferred: the opener first, as without quality steps.
    rows, _, _ = select(Diverse(1, 0.0, quality_share=1.0, quality_margin=2.0), key, (), pool, rep, wanted, params, 3)
    np.testing.assert_array_equal(rows, select(Diverse(1, 0.0), key, (), pool, rep, wanted, params, 3)[0])
    assert int(rows[0]) == 2


@pytest.mark.parametrize("kw, field", [(dict(pool_factor=0), "pool_factor"), (dict(beta=-1.0), "beta"),
                                       (dict(beta=float("nan")), "beta"), (dict(neighbours=0), "neighbours"),
                                       (dict(parent_weight=-1.0), "parent_weight"),
                                       (dict(parent_weight=True), "parent_weight"),
                                       (dict(quality_share=1.5), "quality_share"),
                                       (dict(quality_share=float("nan")), "quality_share"),
                                       (dict(quality_margin=-0.1), "quality_margin"),
                                       (dict(quality_margin=float("inf")), "quality_margin"),
                                       (dict(selection="fast"), "selection"), (dict(rounds=0), "rounds"),
                                       (dict(cap=-1.0), "cap")])
def test_diverse_is_validated(kw, field):
    with pytest.raises(ValueError, match=f"Diverse.{field}="):
        Diverse(**kw)


def test_fallback_shares_by_hand():
    rows = jnp.array([5, 2, 7, 0])  # the rule's choice, best first, from a pool of 8
    wanted = jnp.array([True, True, False, True, True, True, True, True])
    got_rows, rollout, from_model = _share(rows, wanted, jnp.float32(0.5), jnp.bool_(False), 4)
    # 2 from the rule (5, 2), then the pool's first rows not among them (0, 1).
    np.testing.assert_array_equal(got_rows, [5, 2, 0, 1])
    np.testing.assert_array_equal(from_model, [True, True, False, False])
    np.testing.assert_array_equal(rollout, wanted[np.array([5, 2, 0, 1])])
    got_rows, _, from_model = _share(rows, wanted, jnp.float32(0.5), jnp.bool_(True), 4)
    np.testing.assert_array_equal(got_rows, rows)  # warm-up: the rule's rows (its own warm-up choice)


def test_fallback_pursues_the_side_that_opens_more_niches():
    fallback = Fallback(floor=0.1, rate=0.5)
    state = fallback.init()
    added, rejected = int(AddStatus.ADDED), int(AddStatus.REJECTED)
    from_model = jnp.array([True, True, False, False])
    status = jnp.array([added, added, rejected, added])
    ev = Evaluated(jnp.zeros((4, 2)), jnp.zeros(4), jnp.ones(4, bool), status)
    state = fallback.learn(state, from_model, None, ev)
    # Rates: model 2/2, inner 1/2; first averages are the rates; the share moves half way to 0.9.
    np.testing.assert_allclose(state.success, [1.0, 0.5])
    assert float(state.share) == pytest.approx(0.7)
    worse = ev.replace(status=jnp.array([rejected, rejected, added, added]))
    state = fallback.learn(state, from_model, None, worse)
    np.testing.assert_allclose(state.success, [0.5, 0.75])  # 0.5 * old + 0.5 * (0, 1)
    assert float(state.share) == pytest.approx(0.7 + 0.5 * (0.1 - 0.7))
    # A side with no rollouts keeps its average.
    skipped = ev.replace(status=jnp.array([0, 0, added, added]))
    assert float(fallback.learn(state, from_model, None, skipped).success[0]) == pytest.approx(0.5)
    for kw in (dict(floor=0.6), dict(rate=1.5), dict(floor=-0.1)):
        with pytest.raises(ValueError, match=r"Fallback\."):
            Fallback(**kw)
    with pytest.raises(ValueError, match=r"ModelEmitter\.parts: Fallback\(.*\) needs a ranking acquisition rule"):
        ModelEmitter(IsoLine(), Threshold(), parts=(Fallback(),))
    assert isinstance(Fallback().init(), FallbackState)


def test_opener_auc_by_brute_force():
    rng = np.random.default_rng(0)
    novelty = jnp.asarray(np.round(rng.uniform(size=12), 1), jnp.float32)  # rounded: ties happen
    status = jnp.asarray(rng.choice([1, 2, 3], size=12), jnp.int32)
    usable = jnp.asarray(rng.uniform(size=12) < 0.8)
    got = float(compiled(opener_auc)(novelty, Evaluated(jnp.zeros((12, 2)), jnp.zeros(12), usable, status)))
    pos = [float(novelty[i]) for i in range(12) if usable[i] and status[i] == AddStatus.ADDED]
    neg = [float(novelty[i]) for i in range(12) if usable[i] and status[i] != AddStatus.ADDED]
    want = np.mean([1.0 if p > n else 0.5 if p == n else 0.0 for p, n in itertools.product(pos, neg)])
    assert got == pytest.approx(want)
    none = Evaluated(jnp.zeros((12, 2)), jnp.zeros(12), usable, jnp.full(12, 3, jnp.int32))
    assert np.isnan(float(opener_auc(novelty, none)))


def test_the_mqd_preset_is_this_composition_and_spends_exactly_the_population(tiny):
    cfg = tiny(algorithm="mqd", warmup_samples=48, num_batches=5, pool_factor=3, ensemble_size=2, optimism=0.5,
               steering_share=0.3)
    assert cfg.emitter == ModelEmitter(
        IsoLine(scales=(1.0, 2.0)), Diverse(3, 0.5, parent_weight=1.0, quality_share=0.1),
        Surrogate(hidden_size=32, ensemble_size=2, batch_size=16, num_batches=5, features=True, gate=Gate()),
        k=cfg.k, warmup_samples=48, parts=(Steering(share=0.3), Anchoring("auto", "parent"), Fallback()))

    def changed(**options):
        return dataclasses.replace(cfg, algorithm_options={**cfg.options, **options}).emitter

    assert changed(wide_scale=1.0).inner == IsoLine()  # version 0.8's
    assert changed(wide_scale=3.0).inner == IsoLine(scales=(1.0, 3.0))
    assert changed(anchor="nearest").part("anchoring").anchor == "nearest"  # version 0.5's
    assert changed(steering_share=0.0).part("steering") is None  # version 0.4's "mqd"
    assert changed(quality_share=0.0).acquisition == Diverse(3, 0.5, parent_weight=1.0)  # 0.7's
    assert changed(parent_weight=0.0, quality_share=0.0).acquisition == Diverse(3, 0.5)  # 0.6's
    assert changed(opener_cap=2.0).acquisition == Diverse(3, 0.5, parent_weight=1.0, quality_share=0.1, cap=2.0)
    assert changed(novelty_sampling=2.0).surrogate == dataclasses.replace(cfg.emitter.surrogate, novelty_sampling=2.0)
    assert not changed(features=False).surrogate.features and changed(gate=False).surrogate.gate is None  # 0.10's
    state, m = run_mqd(jax.random.PRNGKey(0), cfg)
    pop = cfg.population_size
    np.testing.assert_array_equal(m["evaluations"], pop)
    warm = np.concatenate([[0], np.asarray(m["num_evaluations"])[:-1]]) < cfg.options["warmup_samples"]
    np.testing.assert_array_equal(m["discarded"], np.where(warm, 0, 2 * pop))
    share = np.asarray(m["model_share"])
    np.testing.assert_array_equal(share[warm], 1.0)  # warm-up: the inner emitter's candidates, all "the rule's"
    assert np.all((share[~warm] >= 0.1 - 1e-6) & (share[~warm] <= 0.9 + 1e-6))
    assert state.emitter.surrogate.model.params["params"]["Dense_0"]["bias"].shape[0] == 2
    steered = np.asarray(m["steered"])
    np.testing.assert_array_equal(steered[warm], 0)  # none in warm-up; after it, rollouts of the 14 steered rows
    assert np.all(steered[~warm] <= np.asarray(m["evaluations"])[~warm]) and steered[~warm].sum() > 0


def test_a_rollout_buffer_keeps_the_latest_usable_rollouts_and_training_reads_only_them(linear_task):
    emitter = ModelEmitter(IsoLine(), Diverse(2), Surrogate(num_batches=3, training_data="rollouts", rollout_buffer=8))
    state = compiled(emitter.init)(jax.random.PRNGKey(0), linear_task, 64)
    rep = Repertoire.empty(16, 3, 2, 4)
    params = Params(jnp.float32(0.02), emitter.default_params())
    for step in range(2):  # two generations of 6 candidates, the last of each unusable
        actions = jnp.full((6, 3), step * 0.1) + jnp.arange(6.0)[:, None] * 0.01
        b, q, _ = linear_task.evaluate(actions, None)
        usable = jnp.arange(6) < 5
        proposal = compiled(emitter.propose)(jax.random.PRNGKey(step), state, rep, linear_task, params, 6)
        proposal = proposal.replace(actions=actions, rollout=jnp.ones(6, bool))
        status = jnp.where(usable, int(AddStatus.ADDED), int(AddStatus.SKIPPED))
        state, _ = compiled(emitter.update)(jax.random.PRNGKey(9), state, proposal, Evaluated(b, q, usable, status),
                                            rep, linear_task, params)
    buffer = state.surrogate.rollouts
    assert int(buffer.total) == 10  # 5 usable a generation; the ring of 8 keeps the latest 8
    want = np.concatenate([np.asarray(jnp.arange(5.0) * 0.01) + s * 0.1 for s in range(2)])[-8:]
    got = np.asarray(buffer.actions[(np.arange(10, 18)) % 8, 0])  # oldest first
    np.testing.assert_allclose(got, want, rtol=1e-6)
    # The model trained on the buffer (from the first generation: no warm-up), 3 steps a generation.
    assert int(state.surrogate.model.steps) == 6
    with pytest.raises(ValueError, match=r"Surrogate\.training_data="):
        Surrogate(training_data="archive")
    for bad in (-1.0, float("nan"), True):
        with pytest.raises(ValueError, match=r"Surrogate\.novelty_sampling=.* expected a finite float >= 0"):
            Surrogate(novelty_sampling=bad)
    with pytest.raises(ValueError, match="which training_data='rollouts' does not have"):
        Surrogate(novelty_sampling=2.0, training_data="rollouts")


def flat(cfg):
    """`cfg` as a config dict of version 0.9, when every preset's settings were fields of the config."""
    saved = cfg.to_dict()
    options = saved.pop("algorithm_options")
    later = ("features", "gate", "validity", "step_aside", "training_data", "rollout_buffer",  # options of 0.11, 0.16
             "surrogate", "rule", "curiosity", "opener_cap",  # and the parts of 0.18, the options of 0.23, 0.23.3
             "novelty_sampling")  # and 0.23.4
    return {k: v for k, v in {**saved, **algorithms.options("mqd"), **algorithms.options("mqd-paper"), **options,
                              "adaptation_step_size": 0.1, "adaptation_steps": 10}.items() if k not in later}


def test_mqd_configs_saved_before_version_0_5_do_not_steer_and_before_0_6_anchor_at_the_nearest_skill():
    """... before 0.7 rank predicted openers by their distance alone, before 0.8 make no quality steps and
    before 0.9 vary the pool at one scale; since 0.10 the preset's settings are its options."""
    then = dict(steering_share=0.0, anchor="nearest", parent_weight=0.0, quality_share=0.0, wide_scale=1.0)
    added = ["steering_share", "anchor", "parent_weight", "quality_share", "wide_scale"]  # in 0.5, 0.6, ... 0.9
    for algorithm in ("mqd", "qd", "mqd-paper"):
        for version, missing in enumerate(added):
            saved = {k: v for k, v in flat(Config(algorithm=algorithm)).items() if k not in added[version:]}
            old = {**{k: then[k] for k in added[version:]}, "features": False, "gate": False} \
                if algorithm == "mqd" else {}
            assert config_from(saved) == Config(algorithm=algorithm, algorithm_options=old), (algorithm, missing)
    assert Config(algorithm="mqd").emitter.part("steering") == Steering(0.25)
    # The preset's rule reads its quality share.
    assert Config(algorithm="mqd").emitter.acquisition.quality_share == 0.1
    assert Config(algorithm="mqd", algorithm_options={"quality_share": 0.3}).emitter.acquisition.quality_share == 0.3


def test_configs_saved_before_version_0_3_name_the_papers_filter():
    paper = Config(algorithm="mqd-paper", algorithm_options={"pool_factor": 4})
    old = {k: v for k, v in flat(paper).items() if k not in ("ensemble_size", "optimism")}
    assert config_from({**old, "algorithm": "mqd"}) == paper
    del old["pool_factor"]
    assert config_from({**old, "algorithm": "mqd"}).options["pool_factor"] == 4  # the default then


@pytest.mark.parametrize("exact", [True, False])
def test_nearest_skill_search_matches_brute_force(exact):
    rng = np.random.default_rng(1)
    count, capacity = 700, 2048  # a prefix of 1024 slots holds them
    values = rng.uniform(-1, 1, (capacity, 6)).astype(np.float32)
    rep = Repertoire.empty(capacity, 6, 2, 4).replace(actions=jnp.asarray(values), valid=jnp.arange(capacity) < count,
                                                       count=jnp.int32(count))
    queries = rng.uniform(-1, 1, (50, 6)).astype(np.float32)
    sq, slot = compiled(repertoire_lib.nearest)(rep, rep.actions, jnp.asarray(queries), exact=exact)
    d = ((queries[:, None] - values[None, :count]) ** 2).sum(-1)
    np.testing.assert_array_equal(slot, d.argmin(1))
    np.testing.assert_allclose(sq, d.min(1), rtol=1e-4, atol=1e-5)
    empty_sq, _ = repertoire_lib.nearest(Repertoire.empty(64, 6, 2, 4), rep.actions[:64], jnp.asarray(queries))
    assert np.all(np.isinf(empty_sq))


@pytest.mark.parametrize("count", [0, 2, 700])
def test_k_nearest_skills_match_brute_force(count):
    """The K nearest behaviors in ascending order, ties to the lower slot; missing ones inf with slot -1."""
    rng = np.random.default_rng(2)
    capacity, k = 2048, 4
    behaviors = rng.integers(0, 6, (capacity, 2)).astype(np.float32)  # many ties
    rep = Repertoire.empty(capacity, 1, 2, 4).replace(behaviors=jnp.asarray(behaviors),
                                                      valid=jnp.arange(capacity) < count, count=jnp.int32(count))
    queries = rng.integers(0, 6, (30, 2)).astype(np.float32)
    sq, slots = compiled(repertoire_lib.k_nearest)(rep, jnp.asarray(queries), k)
    d = ((queries[:, None] - behaviors[None, :count]) ** 2).sum(-1)
    order = np.argsort(d, axis=1, kind="stable")[:, :k]
    found = min(count, k)
    np.testing.assert_array_equal(slots[:, :found], order)
    np.testing.assert_array_equal(sq[:, :found], np.take_along_axis(d, order, axis=1))
    assert np.all(slots[:, found:] == -1) and np.all(np.isinf(sq[:, found:]))
