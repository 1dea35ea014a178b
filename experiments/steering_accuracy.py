"""How well one step of the model's Jacobian moves a skill's behavior where it was aimed (what `Steering` relies on).

    python experiments/steering_accuracy.py [--tasks obstacle2d object2d arm] [--generations 100] [--seeds 1]
        [--out docs/data/steering_accuracy.md]

For each task and seed: a run of the "mqd" preset for `--generations` generations; then 800 skills
drawn as IsoLine draws parents (in proportion to novelty), each stepped by the pseudo-inverse of
the model's behavior Jacobian toward a behavior change of s x t_dist in a random direction u
(s = 0.5, 1, 2, 4), every child rolled out. Per step size, over the valid children: the median of
the behavior's change |b' - b| (as a multiple of the aimed s x t_dist), of its cosine to u, and of
the distance between b' and the aim b + s t_dist u. A step the model predicts well moves by about
1 x the aim with a cosine near 1.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import report
from extra_tasks import register_experiment_tasks

from mqd_jax import Config, run_mqd
from mqd_jax.core import selection
from mqd_jax.core.state import get_task
from mqd_jax.emitters import steering

CHILDREN = 800
STEPS = (0.5, 1.0, 2.0, 4.0)


def accuracy(task_name: str, generations: int, seed: int) -> dict[float, tuple[float, float, float]]:
    """Per step size s: (median |change| / (s t_dist), median cosine to the aim, median error / (s t_dist))."""
    cfg = Config.paper(task_name, algorithm="mqd", max_generations=generations)
    state, _ = run_mqd(jax.random.PRNGKey(seed), cfg)
    task, emitter, params, rep = get_task(cfg), cfg.emitter, cfg.params(), state.repertoire
    k_parents, k_direction, k_rollout = jax.random.split(jax.random.PRNGKey(1000 + seed), 3)
    parents = selection.sample_parents(k_parents, rep.novelty, rep.valid, CHILDREN)
    actions, behaviors = rep.actions[parents], rep.behaviors[parents]
    surrogate, known = emitter.surrogate, state.emitter.surrogate
    jacobians = jax.vmap(jax.jacfwd(lambda a: surrogate.predict(known, a, task)[0]))(actions)
    direction = jax.random.normal(k_direction, behaviors.shape)
    direction = direction / jnp.linalg.norm(direction, axis=1, keepdims=True)
    out = {}
    for s in STEPS:
        aim = s * params.t_dist * direction
        child = steering.jacobian_step(actions, jacobians, aim, task)
        reached, _, valid = task.evaluate(child, k_rollout)
        valid = np.asarray(valid)
        change = np.asarray(reached - behaviors)[valid]
        moved = np.linalg.norm(change, axis=1)
        cosine = (change * np.asarray(direction)[valid]).sum(1) / np.maximum(moved, 1e-12)
        error = np.linalg.norm(change - np.asarray(aim)[valid], axis=1)
        unit = s * float(params.t_dist)
        out[s] = (float(np.median(moved)) / unit, float(np.median(cosine)), float(np.median(error)) / unit)
    return out


def main() -> None:
    args = report.probe_arguments(__doc__, ["obstacle2d", "object2d", "arm"], 1, "docs/data/steering_accuracy.md")
    register_experiment_tasks(args.tasks)
    lines = [f"Command: `python experiments/steering_accuracy.py --tasks {' '.join(args.tasks)} --generations "
             f"{args.generations} --seeds {args.seeds}`", "", f"Machine: {report.machine()}.", "",
             f"After {args.generations} generations of \"mqd\": {CHILDREN} novelty-drawn skills per seed, each "
             "stepped by the model's pseudo-inverse Jacobian toward a behavior change of s x t_dist in a random "
             "direction, rolled out. Medians over the valid children, mean over seeds; change and error in units "
             "of the aimed s x t_dist.", "", "| task | s | change / aim | cosine to the aim | error / aim |",
             "|---|---|---|---|---|"]
    for task_name in args.tasks:
        per_seed = [accuracy(task_name, args.generations, seed) for seed in range(args.seeds)]
        for s in STEPS:
            moved, cosine, error = np.mean([r[s] for r in per_seed], axis=0)
            lines.append(f"| {task_name} | {s:g} | {moved:.2f} | {cosine:.2f} | {error:.2f} |")
        print(f"{task_name}: done", flush=True)
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
