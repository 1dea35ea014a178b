"""How often a run's own rollouts open a niche, by their parent's novelty.

    python experiments/open_rate_by_parent.py [--tasks obstacle2d object2d] [--generations 60] [--seeds 3]
        [--compositions mqd] [--out docs/data/open_rate_by_parent.md]

For each task, composition (as `sample_efficiency.py` names them: "mqd", "mqd:parent_weight=2", ...) and seed: a
run from an empty repertoire through ask/tell. Every rollout past warm-up whose candidate names a parent (the skill
it was varied from, `ModelInfo.parents`) is labelled *opened* when it is valid and its behavior lies farther than
t_dist from every skill of the repertoire its generation began with, and placed by its parent's novelty then: its
quantile among the repertoire's skills (fifths, lowest first) and its novelty over the repertoire's median. For the
first third of the generations and the rest, the table gives per fifth the rollouts, their share that opened a niche
and the median relative novelty of their parents; and the slope of log(share) on log(relative novelty) over the
fifths: how steeply the chance that a chosen child opens a niche rises with its parent's novelty after the run's
rule has chosen. A slope of 0: the rule's choice has used what the parent's novelty says; > 0: a child of a sparser
parent still opens more often than the rule's ranking assumes.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np
import report
from extra_tasks import register_experiment_tasks
from opener_signals import _nearest_skill
from sample_efficiency import configured

from mqd_jax import ask, tell
from mqd_jax.core.state import get_task, init

FIFTHS = 5


def rates_by_fifth(quantile: np.ndarray, relative: np.ndarray, opened: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Per fifth of the parents' novelty quantiles [R] (in [0, 1]): the rollouts [5], the share that opened [5]
    (NaN where none), the median relative novelty [5] (NaN where none); and the slope of log(share) on
    log(relative novelty) over the fifths with a share > 0 (NaN where fewer than two)."""
    fifth = np.minimum((quantile * FIFTHS).astype(int), FIFTHS - 1)
    counts = np.bincount(fifth, minlength=FIFTHS)
    share = np.array([opened[fifth == k].mean() if counts[k] else np.nan for k in range(FIFTHS)])
    median = np.array([np.median(relative[fifth == k]) if counts[k] else np.nan for k in range(FIFTHS)])
    usable = np.nan_to_num(share) > 0
    slope = float(np.polyfit(np.log(median[usable]), np.log(share[usable]), 1)[0]) if usable.sum() > 1 else np.nan
    return counts, share, median, slope


def rollouts_by_parent(spec: str, task_name: str, generations: int, seed: int) -> np.ndarray:
    """[R, 4] (generation, parent's novelty quantile, parent's novelty / the median, opened) of a run's rollouts
    past warm-up that name a parent."""
    cfg = configured(spec, task_name, generations)
    task, params = get_task(cfg), cfg.params()
    state, rows = init(jax.random.PRNGKey(seed), cfg), []
    for g in range(generations):
        candidates = ask(state, cfg)
        key = jax.random.fold_in(jax.random.PRNGKey(10_000 + seed), g)
        *outcome, auxiliary = task.evaluate_with_auxiliary(candidates.actions, key, candidates.rollout)
        behaviors, _, valid = outcome
        rep, n = state.repertoire, int(state.repertoire.count)
        parents = getattr(candidates.info, "parents", None)
        if n > 1 and parents is not None and int(state.emitter.evaluations) >= cfg.emitter.warmup_samples:
            novelty = np.asarray(rep.novelty[:n])
            opened = np.asarray(valid) & (_nearest_skill(rep, behaviors) > float(params.t_dist))
            parents = np.asarray(parents)
            chosen = np.asarray(candidates.rollout) & (parents >= 0)
            at = parents[chosen]
            quantile = np.argsort(np.argsort(novelty, kind="stable"), kind="stable") / (n - 1)
            relative = novelty / max(float(np.median(novelty)), 1e-12)
            rows.append(np.stack([np.full(at.shape, g), quantile[at], relative[at], opened[chosen]], axis=1))
        state, _ = tell(state, candidates, *outcome, cfg, auxiliary=auxiliary if task.auxiliary else None)
    return np.concatenate(rows) if rows else np.zeros((0, 4))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["obstacle2d", "object2d"])
    parser.add_argument("--generations", type=int, default=60)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--compositions", nargs="+", default=["mqd"])
    parser.add_argument("--out", default="docs/data/open_rate_by_parent.md")
    args = parser.parse_args()
    register_experiment_tasks(args.tasks)
    for spec in args.compositions:  # refused before anything runs
        configured(spec, args.tasks[0], args.generations)
    third = args.generations // 3
    lines = [f"Command: `python experiments/open_rate_by_parent.py --tasks {' '.join(args.tasks)} --generations "
             f"{args.generations} --seeds {args.seeds} --compositions {' '.join(args.compositions)}`", "",
             f"Machine: {report.machine()}.", "",
             "A run's rollouts past warm-up that name a parent, by the fifth of the repertoire's novelty their parent "
             "was in when its generation began (lowest first): the share that opened a niche, the rollouts, the "
             "parents' median novelty over the repertoire's median, and the slope of log(share) on log(relative "
             "novelty) (0: the rule's choice has used the parent's novelty; > 0: children of sparser parents open "
             "more than it assumed). All seeds together.", ""]
    for task_name in args.tasks:
        lines += [f"### {task_name}", "",
                  "| composition | generations | share that opened, by fifth | rollouts | relative novelty | slope |",
                  "|---|---|---|---|---|---|"]
        for spec in args.compositions:
            rows = np.concatenate([rollouts_by_parent(spec, task_name, args.generations, seed)
                                   for seed in range(args.seeds)])
            for low, high in ((0, third), (third, args.generations)):
                part = rows[(rows[:, 0] >= low) & (rows[:, 0] < high)]
                counts, share, median, slope = rates_by_fifth(part[:, 1], part[:, 2], part[:, 3].astype(bool))
                lines.append(f"| {spec} | {low + 1}-{high} | {' / '.join(f'{s:.3f}' for s in share)} | "
                             f"{' / '.join(str(c) for c in counts)} | {' / '.join(f'{m:.2f}' for m in median)} | "
                             f"{slope:.2f} |")
            print(f"{task_name} {spec}: done", flush=True)
        lines.append("")
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
