"""Which signals tell a niche-opener from the rest of a pool, and how rugged a task is under QD's mutation.

    python experiments/opener_signals.py [--tasks obstacle2d object2d] [--generations 100] [--seeds 2]
        [--pools 4] [--ensemble 1] [--surrogate network] [--curiosity 0] [--novelty_sampling 0]
        [--out docs/data/opener_signals_v20.md]

For each task and seed: a run of the "mqd" preset for `--generations` generations, then `--pools`
pools of 8 x 100 IsoLine children of its final repertoire (what "mqd" chooses its rollouts
from), every child rolled out. An *opener* is a valid child whose true behavior lies farther than
t_dist from every skill (it would open a niche). For each signal, over the pools:

  * AUC: P(an opener scores higher than a non-opener), ties 1/2 (0.5 = chance);
  * precision@100: the fraction of openers among the 100 best-scored children (what a
    generation of 100 rollouts chosen by that signal alone would open; the pool's base rate and
    the oracle's, which ranks by the true outcome, bound it).

Signals: the run's model (plain and anchored predictions, as `ModelEmitter.predictions`) scored by the distance to
the nearest skill (what `Diverse` ranks by) or by a smoothed novelty (mean distance to the 5 nearest skills; minus
the number of skills within 0.1); the parent's novelty (the repertoire's, by which IsoLine draws parents); networks
trained afresh for 2000 Adam steps on the repertoire, or on the repertoire and the archive of rejected rollouts, or
on the repertoire with the task's features as inputs (`Task.features`), with their held-out behavior error (MSE over
the pools' valid children); and a classifier of openers (a network of 64 units fitted for 3000 steps of 64 rows to +1
for an opener and -1 for the rest) trained on the seed's other pools, every child of which was rolled out, and scored
on the held-out pool: what a model of the action alone can learn of "would open a niche" from more labelled rollouts
of the same repertoire than a run ever has. Three leads of issue 68: the run's own classifier of openers (the same
network fitted to what the run's last 20 generations' rollouts did: opened a niche of the repertoire their generation
began with, or not; run through ask/tell), alone and with its rank multiplied by the anchored novelty-5's; and a
model relative to the parent (a network fitted on the other pools to the change of behavior from the parent's, from
the parent's action and the child's step), scored at the parent's behavior plus the predicted change; with
`--ensemble E` ("mqd" with E members), the members' spread alone and added to the anchored distance (optimism, as
`Diverse` ranks with an ensemble). With `--surrogate local` the run is "mqd-local" (`LocalLinear` in place of the
network, `mqd_jax.surrogate.local`), and "the run's model" rows are its predictions. With `--curiosity W` the run has
`Curiosity(W)` (`mqd_jax.emitters.curiosity`), and the signals of its record: the factor of each child's parent's
record, and the anchored distance times the parent's novelty (what `Diverse` ranks by, `parent_weight=1`), with and
without the factor. With `--novelty_sampling P` the run's model trains on mini-batches drawn by novelty ** P
(`Surrogate.novelty_sampling`). Two rankings that use only what a run could know (0.23.2): P(open), the share of 32
points (the child's anchored prediction plus a residual drawn from the other pools' held-out anchored errors) that
lie farther than t_dist from every skill, the model's error taken as it is rather than as zero; and a logistic
regression, fitted on the other pools, of "opened" on six of the child's signals (its anchored nearest distance,
novelty-5 and count within 0.1, its parent's novelty, its step from the parent and its predicted behavior's distance
from the parent's): whether the weak signals combine. And what the run's own choices open: of its last 20
generations' rollouts past warm-up, the share that opened a niche, by source (`SOURCES`: the rule's choice of the
inner emitter's children, of steered children, and the fallback's fill, which the model did not rank: the run's own
base rate; opened: farther than t_dist from every skill its generation began with). And the task's ruggedness:
quartiles of the distance between a child's behavior and its first parent's. Every child is rolled out: quick on the
2D tasks and the planar arm of sample_efficiency.py (`--tasks arm`), minutes on a robot task (C MuJoCo).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import report
from extra_tasks import register_experiment_tasks

from mqd_jax import Config, ask, tell
from mqd_jax.core import repertoire as repertoire_lib
from mqd_jax.core.archive import Archive
from mqd_jax.core.run import run_generations
from mqd_jax.core.state import get_task, init
from mqd_jax.core.task import Task
from mqd_jax.emitters.parts import Pooled
from mqd_jax.surrogate import model

POOL, CHOSEN = 800, 100
HISTORY = 20  # the run's last generations whose rollouts' outcomes its own classifier of openers learns
DRAWS = 32  # points per child of P(open): its anchored prediction plus as many held-out residuals
# Where a run's own rollouts came from: the rule's choice of the inner emitter's children, of steered children, and the
# fallback's fill (the inner emitter's first candidates, unranked: the run's own base rate).
SOURCES = ("the rule's choice, not steered", "the rule's choice, steered", "the fallback's fill (unranked)")


def auc(score: np.ndarray, label: np.ndarray) -> float:
    """P(score of a positive > score of a negative), ties 1/2; NaN without both."""
    pos, neg = score[label], score[~label]
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    return float(((pos[:, None] > neg[None]) + 0.5 * (pos[:, None] == neg[None])).mean())


def _scores(predicted: np.ndarray, skills: np.ndarray) -> dict[str, np.ndarray]:
    """Scores [N] of predicted behaviors [N, d] against the repertoire's behaviors [n, d]: nearest distance,
    mean distance to the 5 nearest, minus the count within 0.1."""
    d = np.linalg.norm(predicted[:, None] - skills[None], axis=-1)
    nearest = np.sort(d, axis=1)
    return {"nearest": nearest[:, 0], "novelty-5": nearest[:, :5].mean(1), "-count(0.1)": -(d < 0.1).sum(1)}


def _fresh(data: repertoire_lib.Repertoire | Archive, hidden: int, task: Task, key: jax.Array,
           features: bool = False) -> model.ModelState:
    """A network of `hidden` units trained afresh for 2000 steps of 16 rows on `data` (`features`: with the task's
    features as inputs, computed for 4096 rows drawn from the data)."""
    state = model.init(key, hidden, task, features=features)
    return jax.jit(lambda s: model.train(s, jax.random.fold_in(key, 1), data, task, 1e-3, 16, 2000,
                                         4096 if features else None))(state)[0]


def top_rows(score: np.ndarray) -> np.ndarray:
    """The rows of the `CHOSEN` best scores [N], best first (ties: the first in the pool)."""
    return np.argsort(-score, kind="stable")[:CHOSEN]


def precision(score: np.ndarray, opener: np.ndarray) -> float:
    """Precision@100: the share of openers [N] among the `CHOSEN` best-scored rows."""
    return float(opener[top_rows(score)].mean())


def _rated(score: np.ndarray, opener: np.ndarray, error: float = float("nan")) -> tuple[float, float, float]:
    """(AUC, precision@100, held-out behavior error) of scores [N] against the openers [N]."""
    return auc(score, opener), precision(score, opener), error


def _predictions(emitter: Any, state: Any, pool: Any, rep: Any, task: Task) -> tuple[jax.Array, jax.Array]:
    """The run's model's plain and anchored predictions [E, N, d + 1] of the pool's actions, as "mqd"'s
    `Anchoring` makes them (at the parents the pool names)."""
    x = emitter.model.inputs(pool.actions, task)
    plain = emitter.model.overrule(state.surrogate, x, emitter.model.members(state.surrogate, pool.actions, task, x),
                                   task)
    view = emitter.view(state, rep, task, None, pool.actions.shape[0])
    return plain, emitter.part("anchoring").anchored(Pooled(pool.actions, pool.parents, x, plain), view)


def _relative_data(actions: jax.Array, behaviors: jax.Array, valid: jax.Array, rep: Any, parents: np.ndarray,
                   task: Task) -> tuple[jax.Array, jax.Array, np.ndarray]:
    """Inputs [N, 2n] (the parent's normalized action, the child's step from it), targets [N, d] (the child's
    behavior's change from the parent's, in behavior-box units) and which rows are usable (valid, a parent)."""
    parent_actions = model.normalize_actions(rep.actions[np.maximum(parents, 0)], task)
    child = model.normalize_actions(actions, task)
    scale = jnp.asarray(task.behavior_high) - jnp.asarray(task.behavior_low)
    targets = jnp.clip((behaviors - rep.behaviors[np.maximum(parents, 0)]) / scale, -1, 1)
    return jnp.concatenate([parent_actions, child - parent_actions], axis=1), targets, \
        np.asarray(valid) & (parents >= 0)


def _relative(data: list[tuple[jax.Array, jax.Array, np.ndarray]], task: Task, key: jax.Array) -> model.ModelState:
    """A network of 64 units fitted for 3000 steps of 64 rows to the change of behavior from the parent's, on the
    usable rows of `data` (`_relative_data`'s, at least one pool)."""
    return _fitted(jnp.concatenate([x[ok] for x, _, ok in data]), jnp.concatenate([y[ok] for _, y, ok in data]),
                   model.init(key, 64, task, out_size=task.behavior_dim, input_size=2 * task.action_dim),
                   jax.random.fold_in(key, 3))


def _fitted(inputs: jax.Array, targets: jax.Array, network: model.ModelState, key: jax.Array) -> model.ModelState:
    """`network` fitted for 3000 steps of 64 rows to targets [R, out] from inputs [R, in]."""
    fit = jax.jit(lambda s: model.fit(s, key, inputs, targets, jnp.int32(inputs.shape[0]), 1e-3, 64, 3000))
    return fit(network)[0]


def _nearest_skill(rep: Any, behaviors: jax.Array) -> np.ndarray:
    """Each behavior's [N] distance to the nearest skill of `rep` (inf where it holds none)."""
    return np.sqrt(np.asarray(repertoire_lib.k_nearest(rep, behaviors, 1)[0][:, 0]))


def _p_open(predicted: np.ndarray, residuals: np.ndarray, rep: Any, t_dist: float, task: Task,
            rng: np.random.Generator) -> np.ndarray:
    """P(open) of predictions [N, d] under held-out errors residuals [R, d]: the share of `DRAWS` points, each the
    prediction plus a residual drawn uniformly, clipped to the behavior box, farther than t_dist from every skill."""
    draws = predicted[:, None] + residuals[rng.integers(0, len(residuals), (len(predicted), DRAWS))]
    points = np.clip(draws, task.behavior_low, task.behavior_high).reshape(-1, predicted.shape[1])
    return (_nearest_skill(rep, jnp.asarray(points, jnp.float32)).reshape(len(predicted), DRAWS) > t_dist).mean(1)


def _candidate_features(scored: dict[str, np.ndarray], step: np.ndarray, displacement: np.ndarray,
                        t_dist: float) -> np.ndarray:
    """[N, 6] what the rule can know of each child: the anchored prediction's distance to the nearest skill and its
    novelty-5 (logs, in t_dist), minus its count within 0.1, the parent's novelty (log), the child's step from its
    parent (log, normalized action units) and its predicted behavior's from the parent's (log, in t_dist)."""
    log = lambda x: np.log(np.maximum(x, 1e-6))  # noqa: E731
    return np.stack([log(scored["run's model, anchored, nearest"] / t_dist),
                     log(scored["run's model, anchored, novelty-5"] / t_dist),
                     scored["run's model, anchored, -count(0.1)"] / 10.0, log(scored["parent's novelty"] / t_dist),
                     log(step), log(displacement / t_dist)], axis=1)


def _logistic(x: np.ndarray, label: np.ndarray, ridge: float = 1e-2, steps: int = 50) -> Any:
    """A logistic regression of label [R] on standardized x [R, f] (Newton steps, ridge on the weights): the
    function of x [N, f] that gives the log-odds."""
    mean, std = x.mean(0), x.std(0) + 1e-9
    design = lambda x: np.c_[(x - mean) / std, np.ones(len(x))]  # noqa: E731
    z, w = design(x), np.zeros(x.shape[1] + 1)
    for _ in range(steps):
        p = 1.0 / (1.0 + np.exp(-z @ w))
        hessian = (z * (p * (1 - p))[:, None]).T @ z + ridge * np.eye(len(w))
        w -= np.linalg.solve(hessian, z.T @ (p - label) + ridge * w)
    return lambda x: design(x) @ w


def _rank(score: np.ndarray) -> np.ndarray:
    """Each score's rank in (0, 1], the highest 1."""
    return (np.argsort(np.argsort(score, kind="stable"), kind="stable") + 1) / len(score)


def _classifier(labelled: list[tuple[jax.Array, np.ndarray]], task: Task, key: jax.Array) -> model.ModelState:
    """A network of 64 units fitted for 3000 steps of 64 rows to +1 (opener) / -1 on [(normalized actions [N, n],
    openers [N])], at least one pool."""
    targets = jnp.concatenate([jnp.where(o, 1.0, -1.0) for _, o in labelled])[:, None]
    return _fitted(jnp.concatenate([x for x, _ in labelled]), targets, model.init(key, 64, task, out_size=1),
                   jax.random.fold_in(key, 2))


def _run_with_history(cfg: Config, seed: int, last: int) -> tuple[Any, list[tuple[jax.Array, np.ndarray]],
                                                                  dict[str, list[int]]]:
    """The run of `cfg` from `seed` (as `run_mqd`'s generations, its last `last` through ask/tell), what those
    last generations' rollouts teach about openers: [(normalized actions [R, n], opened [R])], one per generation,
    opened = valid and farther than t_dist from every skill of the repertoire its generation began with; and, past
    warm-up, {source: [rollouts, openers]} of those rollouts by where they came from (`SOURCES`)."""
    task, params = get_task(cfg), cfg.params()
    first = jax.jit(lambda k: run_generations(init(k, cfg), cfg, params, cfg.max_generations - last)[0])
    state = first(jax.random.PRNGKey(seed))
    history, sources = [], {name: [0, 0] for name in SOURCES}
    for g in range(last):
        candidates = ask(state, cfg)
        key = jax.random.fold_in(jax.random.PRNGKey(10_000 + seed), g)
        *outcome, auxiliary = task.evaluate_with_auxiliary(candidates.actions, key, candidates.rollout)
        behaviors, _, valid = outcome
        distance = _nearest_skill(state.repertoire, behaviors)
        rolled = np.asarray(candidates.rollout)
        opened = np.asarray(valid) & (distance > float(params.t_dist))
        history.append((model.normalize_actions(candidates.actions[rolled], task), opened[rolled]))
        if int(state.emitter.evaluations) >= cfg.emitter.warmup_samples:  # the model chose this generation's rows
            info = candidates.info
            steered = np.asarray(info.parts["steering"][0]) if "steering" in info.parts else np.zeros_like(rolled)
            chosen = np.asarray(info.from_model)
            for name, rows in zip(SOURCES, (chosen & ~steered, chosen & steered, ~chosen), strict=True):
                sources[name][0] += int((rows & rolled).sum())
                sources[name][1] += int((rows & rolled & opened).sum())
        state, _ = tell(state, candidates, *outcome, cfg, auxiliary=auxiliary if task.auxiliary else None)
    return state, history, sources


def signals(task_name: str, generations: int, seed: int, pools: int, ensemble: int = 1, surrogate: str = "network",
            curiosity: int = 0, novelty_sampling: int = 0) -> tuple[dict[str, list], dict[str, float]]:
    """Per signal, [(AUC, precision@100)] over the pools; and the ruggedness quartiles, the base rate and the
    number of skills. `ensemble` > 1: "mqd" with that many members, and the signals of their spread; `surrogate`
    "local": "mqd-local"; `curiosity` > 0: with `Curiosity(curiosity)`, and the signals of its record;
    `novelty_sampling` > 0: the run's model trained on mini-batches drawn by novelty to that power."""
    options = ({"ensemble_size": ensemble} if ensemble > 1 else {}) | (
        {"curiosity": float(curiosity)} if curiosity else {}) | (
        {"novelty_sampling": float(novelty_sampling)} if novelty_sampling else {})
    cfg = Config.paper(task_name, algorithm="mqd-local" if surrogate == "local" else "mqd",
                       max_generations=generations, algorithm_options=options)
    state, history, sources = _run_with_history(cfg, seed, HISTORY)
    task, emitter, params, rep = get_task(cfg), cfg.emitter, cfg.params(), state.repertoire
    n, filled = int(rep.count), min(int(state.archive.total), state.archive.qualities.shape[0])
    skills = np.asarray(rep.behaviors[:n])
    arch = state.archive
    both = Archive(jnp.concatenate([rep.actions[:n], arch.actions[:filled]]),
                   jnp.concatenate([rep.behaviors[:n], arch.behaviors[:filled]]),
                   jnp.concatenate([rep.qualities[:n], arch.qualities[:filled]]), jnp.int32(n + filled))
    key = jax.random.PRNGKey(1000 + seed)
    fresh = {f"fresh {h} units, {name}": _fresh(data, h, task, key)
             for h in (32, 256) for name, data in (("repertoire", rep), ("repertoire + archive", both))}
    fresh |= {f"fresh {h} units, repertoire, with the task's features": _fresh(rep, h, task, key, True)
              for h in (32, 256)}
    out: dict[str, list] = {}
    distances, openers, labelled, ranked, relative, parents_of = [], [], [], [], [], []
    residuals, described = [], []  # per pool: (anchored predictions, behaviors, valid); `_candidate_features`
    for p in range(pools):
        k = jax.random.fold_in(key, p)
        pool = emitter.inner.propose(k, state.emitter.inner, rep, task, params.part(params.emitter.inner), POOL)
        parents = np.asarray(pool.parents)  # the skill each child was varied from, as the proposal names it
        behaviors, _, valid = task.evaluate(pool.actions, k)
        true_d = _nearest_skill(rep, behaviors)
        opener = (true_d > float(params.t_dist)) & np.asarray(valid)
        openers.append(opener.mean())
        parents_of.append(parents)
        distances.append(np.linalg.norm(np.asarray(behaviors) - np.asarray(rep.behaviors)[parents], axis=1)[
            np.asarray(valid)])
        plain, anchored = _predictions(emitter, state.emitter, pool, rep, task)
        scored = {f"run's model, {name}, {s}": v
                  for name, y in (("plain", plain), ("anchored", anchored))
                  for s, v in _scores(np.asarray(y.mean(0)[:, :-1]), skills).items()}
        predicted = {name: np.asarray(model.predict(m, pool.actions, task, "features" in name)[0])
                     for name, m in fresh.items()}
        scored |= {f"{name}, nearest": _scores(y, skills)["nearest"] for name, y in predicted.items()}
        if ensemble > 1:  # lead 3: the members' disagreement on the behavior, alone and as optimism
            spread = np.sqrt(np.asarray(anchored)[:, :, :-1].var(axis=0).sum(-1))
            scored["ensemble's spread (anchored)"] = spread
            scored["anchored nearest + spread (optimistic)"] = scored["run's model, anchored, nearest"] + spread
        ok = np.asarray(valid)
        error = {f"{name}, nearest": float(np.mean((y[ok] - np.asarray(behaviors)[ok]) ** 2))
                 for name, y in predicted.items()}
        scored["parent's novelty"] = np.asarray(rep.novelty)[parents]
        if curiosity:  # the run's record of each parent's children that opened niches (`Curiosity`)
            part = next(x for x in emitter.parts if x.name == "curiosity")
            record = np.asarray(part.factor(state.emitter.parts["curiosity"], pool.parents, rep))
            ranks = scored["run's model, anchored, nearest"] * scored["parent's novelty"]
            scored["parent's record (Curiosity's factor)"] = record
            scored["anchored nearest x parent's novelty (Diverse's rank)"] = ranks
            scored["anchored nearest x parent's novelty x record (with Curiosity)"] = ranks * record
        scored["oracle (true distance)"] = np.where(np.asarray(valid), true_d, -np.inf)
        guess = np.asarray(anchored.mean(0)[:, :-1])
        residuals.append((guess, np.asarray(behaviors), ok))
        child = model.normalize_actions(pool.actions, task)
        step = np.linalg.norm(np.asarray(child - model.normalize_actions(rep.actions[parents], task)), axis=1)
        displacement = np.linalg.norm(guess - np.asarray(rep.behaviors)[parents], axis=1)
        described.append(_candidate_features(scored, step, displacement, float(params.t_dist)))
        labelled.append((child, opener))
        relative.append(_relative_data(pool.actions, behaviors, valid, rep, parents, task))
        ranked.append(scored["run's model, anchored, novelty-5"])
        for name, score in scored.items():
            out.setdefault(name, []).append(_rated(score, opener, error.get(name, float("nan"))))
    for p, (inputs, opener) in enumerate(labelled if pools > 1 else []):  # one pool has no other to learn from
        score = np.asarray(model.apply_members(_classifier(labelled[:p] + labelled[p + 1:], task, key), inputs))
        out.setdefault("classifier of openers, other pools", []).append(_rated(score[0, :, 0], opener))
    for p, (inputs, _, _) in enumerate(relative if pools > 1 else []):
        delta = _relative(relative[:p] + relative[p + 1:], task, key)
        scale = np.asarray(task.behavior_high) - np.asarray(task.behavior_low)
        predicted = np.asarray(rep.behaviors)[parents_of[p]] + np.asarray(model.apply_members(delta, inputs))[0] * scale
        for name, score in _scores(predicted, skills).items():
            out.setdefault(f"relative to the parent (other pools), {name}", []).append(_rated(score, labelled[p][1]))
    rng = np.random.default_rng(seed)
    for p, (guess, _, _) in enumerate(residuals if pools > 1 else []):
        errors = np.concatenate([(b - g)[ok] for q, (g, b, ok) in enumerate(residuals) if q != p])
        out.setdefault("run's model, anchored, P(open) under the other pools' residuals", []).append(
            _rated(_p_open(guess, errors, rep, float(params.t_dist), task, rng), labelled[p][1]))
        odds = _logistic(np.concatenate(described[:p] + described[p + 1:]),
                         np.concatenate([o for q, (_, o) in enumerate(labelled) if q != p]))
        out.setdefault("logistic regression on the child's six signals (other pools)", []).append(
            _rated(odds(described[p]), labelled[p][1]))
    own = _classifier(history, task, key)  # what the run itself has seen open niches, its last generations
    for p, (inputs, opener) in enumerate(labelled):
        score = np.asarray(model.apply_members(own, inputs))[0, :, 0]
        out.setdefault(f"classifier of the run's own openers, last {HISTORY} generations", []).append(
            _rated(score, opener))
        novelty = ranked[p]
        out.setdefault("the run's own classifier x anchored novelty-5 (ranks multiplied)", []).append(
            _rated(_rank(score) * _rank(novelty), opener))
    quantiles = np.quantile(np.concatenate(distances), [0.25, 0.5, 0.75])
    return out, {"base rate": float(np.mean(openers)), **{f"q{q}": v for q, v in zip((25, 50, 75), quantiles,
                                                                                         strict=True)}, "skills": n,
                 **{f"{name}: {what}": float(count) for name, counts in sources.items()
                    for what, count in zip(("rollouts", "openers"), counts, strict=True)}}


def main() -> None:
    args = report.probe_arguments(__doc__, ["obstacle2d", "object2d"], 2, "docs/data/opener_signals_v20.md",
                                  {"surrogate": ("network", "local")}, pools=4, ensemble=1, curiosity=0,
                                  novelty_sampling=0)
    register_experiment_tasks(args.tasks)
    lines = [f"Command: `python experiments/opener_signals.py --tasks {' '.join(args.tasks)} --generations "
             f"{args.generations} --seeds {args.seeds} --pools {args.pools}"
             + (f" --ensemble {args.ensemble}" if args.ensemble > 1 else "")
             + (f" --curiosity {args.curiosity}" if args.curiosity else "")
             + (f" --novelty_sampling {args.novelty_sampling}" if args.novelty_sampling else "")
             + (f" --surrogate {args.surrogate}`" if args.surrogate != "network" else "`"), "",
             f"Machine: {report.machine()}.", "",
             f"After {args.generations} generations of \"mqd\""
             + (" with `LocalLinear`" if args.surrogate == "local" else "")
             + (f" with `Curiosity({args.curiosity})`" if args.curiosity else "")
             + (f" with `novelty_sampling={args.novelty_sampling}`" if args.novelty_sampling else "")
             + f": {args.pools} pools of {POOL} IsoLine children per seed, all rolled out; an opener would open a "
             f"niche. AUC: P(opener scores higher), 0.5 = chance; "
             f"precision@{CHOSEN}: openers among the {CHOSEN} best-scored. Mean over seeds and pools.", ""]
    for task_name in args.tasks:
        per_seed = [signals(task_name, args.generations, seed, args.pools, args.ensemble, args.surrogate,
                            args.curiosity, args.novelty_sampling) for seed in range(args.seeds)]
        stats = {k: np.mean([s[1][k] for s in per_seed]) for k in per_seed[0][1]}
        lines += [f"### {task_name}", "",
                  f"Skills after {args.generations} generations: {stats['skills']:.0f}; openers in a pool (base "
                  f"rate): {stats['base rate']:.3f}; distance from a valid child's behavior to its first parent's "
                  f"(quartiles): {stats['q25']:.3f} / {stats['q50']:.3f} / {stats['q75']:.3f} (t_dist 0.02).", "",
                  "| signal | AUC | precision@100 | held-out behavior MSE |", "|---|---|---|---|"]
        for name in per_seed[0][0]:
            values = np.array([v for s in per_seed for v in s[0][name]], float)
            mse = "" if np.isnan(values[:, 2]).all() else f"{np.nanmean(values[:, 2]):.5f}"
            lines.append(f"| {name} | {np.nanmean(values[:, 0]):.3f} | {values[:, 1].mean():.3f} | {mse} |")
        lines.append("")
        lines += [f"The run's own rollouts of its last {HISTORY} generations past warm-up, by source (all seeds):", "",
                  "| source | rollouts | share that opened a niche |", "|---|---|---|"]
        for name in SOURCES:
            rolled, opened = (sum(s[1][f"{name}: {what}"] for s in per_seed) for what in ("rollouts", "openers"))
            lines.append(f"| {name} | {rolled:.0f} | {opened / rolled if rolled else float('nan'):.3f} |")
        lines.append("")
        print(f"{task_name}: done", flush=True)
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
