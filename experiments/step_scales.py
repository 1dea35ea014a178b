"""How a child's step size bears on the niches it opens and on the model's ranking, and where the model's first
choices err.

    python experiments/step_scales.py [--tasks obstacle2d object2d] [--generations 100] [--seeds 4] [--pools 2]
        [--out docs/data/step_scales_100.md]

For each task and seed: a run of the "mqd" preset for `--generations` generations (as `opener_signals.py`'s), then
per step scale s in `SCALES` `--pools` pools of 800 IsoLine children of its repertoire with both iso+line steps
multiplied by s ("mqd"'s own pool: half at 1, half at 2), every child rolled out. An opener is a valid child
farther than t_dist from every skill. Per scale, averaged over seeds and pools:

  * the pool's share of openers (base rate);
  * the median distance from a valid child's behavior to its parent's, true and as the run's model predicts it
    (anchored at the parent, as `Anchoring` does), and the median cosine between the two displacements;
  * precision@100 (openers among the 100 best-scored) of the anchored prediction's distance to the nearest skill,
    of that distance times the parent's novelty (what `Diverse` ranks by), and of the oracle (the true distance).

At scale 1, where the model's first choices err: the model's error (distance from the anchored prediction to the true
behavior, in t_dist) over the valid children (quartiles, 90th percentile) and over the 100 it predicts farthest from
every skill (median), the median predicted and true nearest distance of those 100 and of the openers; and the
precision@100 of the predicted distance capped at t_dist (every predicted opener alike) times the parent's novelty.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import report
from extra_tasks import register_experiment_tasks
from opener_signals import POOL, _nearest_skill, _predictions, precision, top_rows

from mqd_jax import Config
from mqd_jax.core.run import run_generations
from mqd_jax.core.state import get_task, init
from mqd_jax.emitters.baselines import IsoLine

SCALES = (0.25, 0.5, 1.0, 2.0)
SCALE_COLUMNS = ("base rate", "true displacement", "predicted displacement", "cosine", "precision: nearest",
                 "precision: nearest x parent's novelty", "precision: oracle")
ERROR_COLUMNS = ("error q25", "error median", "error q75", "error p90", "top 100: error median",
                 "top 100: predicted nearest", "top 100: true nearest", "openers: predicted nearest",
                 "openers: true nearest", "precision: min(nearest, t_dist) x parent's novelty")


def _pool(state: Any, cfg: Config, scale: float, key: jax.Array) -> dict[str, np.ndarray]:
    """One pool of IsoLine children at `scale`, rolled out, with what the run's model predicts of them."""
    task, params, emitter, rep = get_task(cfg), cfg.params(), cfg.emitter, state.repertoire
    inner = params.part(params.emitter.inner)
    pool = IsoLine(scales=(scale,)).propose(key, state.emitter.inner, rep, task, inner, POOL)
    behaviors, _, valid = task.evaluate(pool.actions, key)
    anchored = np.asarray(_predictions(emitter, state.emitter, pool, rep, task)[1].mean(0)[:, :-1])
    parents = np.asarray(pool.parents)
    true_nearest = _nearest_skill(rep, behaviors)
    return {"behaviors": np.asarray(behaviors), "valid": np.asarray(valid), "predicted": anchored,
            "parent": np.asarray(rep.behaviors)[parents], "novelty": np.asarray(rep.novelty)[parents],
            "true nearest": true_nearest, "predicted nearest": _nearest_skill(rep, jnp.asarray(anchored)),
            "opener": (true_nearest > float(params.t_dist)) & np.asarray(valid)}


def _by_scale(p: dict[str, np.ndarray]) -> list[float]:
    """`SCALE_COLUMNS` of one rolled-out pool (`_pool`)."""
    ok, opener = p["valid"], p["opener"]
    true_step, guessed_step = p["behaviors"] - p["parent"], p["predicted"] - p["parent"]
    true_norm, guessed_norm = np.linalg.norm(true_step, axis=1), np.linalg.norm(guessed_step, axis=1)
    cosine = (true_step * guessed_step).sum(1) / np.maximum(true_norm * guessed_norm, 1e-12)
    oracle = np.where(ok, p["true nearest"], -np.inf)
    return [opener.mean(), np.median(true_norm[ok]), np.median(guessed_norm[ok]), np.median(cosine[ok]),
            precision(p["predicted nearest"], opener), precision(p["predicted nearest"] * p["novelty"], opener),
            precision(oracle, opener)]


def _errors(p: dict[str, np.ndarray], t_dist: float) -> list[float]:
    """`ERROR_COLUMNS` of one rolled-out pool (`_pool`): errors and nearest distances in t_dist."""
    ok, opener, guessed = p["valid"], p["opener"], p["predicted nearest"]
    error = np.linalg.norm(p["predicted"] - p["behaviors"], axis=1) / t_dist
    top = top_rows(guessed)
    capped = np.minimum(guessed, t_dist) * p["novelty"]
    return [*np.quantile(error[ok], [0.25, 0.5, 0.75, 0.9]), np.median(error[top]), np.median(guessed[top]) / t_dist,
            np.median(p["true nearest"][top]) / t_dist, np.median(guessed[opener]) / t_dist if opener.any() else np.nan,
            np.median(p["true nearest"][opener]) / t_dist if opener.any() else np.nan, precision(capped, opener)]


def measure(task_name: str, generations: int, seed: int, pools: int) -> tuple[dict[float, list], list, float]:
    """{scale: [SCALE_COLUMNS per pool]}, [ERROR_COLUMNS per pool at scale 1] and the skills after the run."""
    cfg = Config.paper(task_name, algorithm="mqd", max_generations=generations)
    params = cfg.params()
    state = jax.jit(lambda k: run_generations(init(k, cfg), cfg, params, generations)[0])(jax.random.PRNGKey(seed))
    by_scale: dict[float, list] = {}
    errors = []
    for scale in SCALES:
        for p in range(pools):
            pool = _pool(state, cfg, scale, jax.random.fold_in(jax.random.PRNGKey(1000 + seed), p))
            by_scale.setdefault(scale, []).append(_by_scale(pool))
            if scale == 1.0:
                errors.append(_errors(pool, float(params.t_dist)))
    return by_scale, errors, float(state.repertoire.count)


def main() -> None:
    args = report.probe_arguments(__doc__, ["obstacle2d", "object2d"], 4, "docs/data/step_scales_100.md", pools=2)
    register_experiment_tasks(args.tasks)
    lines = [f"Command: `python experiments/step_scales.py --tasks {' '.join(args.tasks)} --generations "
             f"{args.generations} --seeds {args.seeds} --pools {args.pools} --out {args.out}`", "",
             f"Machine: {report.machine()}.", "",
             f"After {args.generations} generations of \"mqd\": {args.pools} pools of {POOL} IsoLine children per seed "
             "and step scale (x both iso+line steps), all rolled out; an opener would open a niche. Displacement: the "
             "median distance from a valid child's behavior to its parent's, true and as the run's anchored model "
             "predicts it; cosine: the median cosine between the two. Precision: openers among the 100 best-scored. "
             "Error: from the anchored prediction to the true behavior, in t_dist; top 100: the children predicted "
             "farthest from every skill (nearest distances in t_dist). Mean over seeds and pools.", ""]
    for task_name in args.tasks:
        runs = [measure(task_name, args.generations, seed, args.pools) for seed in range(args.seeds)]
        lines += [f"### {task_name}", "", f"Skills: {np.mean([r[2] for r in runs]):.0f}.", "",
                  "| step scale | " + " | ".join(SCALE_COLUMNS) + " |", "|---" * (len(SCALE_COLUMNS) + 1) + "|"]
        for scale in SCALES:
            values = np.nanmean([v for r in runs for v in r[0][scale]], axis=0)
            lines.append(f"| {scale:g} | " + " | ".join(f"{v:.3f}" for v in values) + " |")
        values = np.nanmean([v for r in runs for v in r[1]], axis=0)
        lines += ["", "At scale 1:", "", "| " + " | ".join(ERROR_COLUMNS) + " |", "|---" * len(ERROR_COLUMNS) + "|",
                  "| " + " | ".join(f"{v:.3f}" if "precision" in c else f"{v:.2f}"
                                    for c, v in zip(ERROR_COLUMNS, values, strict=True)) + " |", ""]
        print(f"{task_name}: done", flush=True)
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
