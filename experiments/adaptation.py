"""Skill adaptation on final M-QD repertoires: nearest neighbour vs local linearization vs model Jacobian.

    python experiments/adaptation.py [--tasks obstacle2d object2d] [--repertoires 25] [--goals 1000]
                                     [--out results/adaptation]

The paper's protocol ("Results: Adaptation of skills"): for each task, build
`--repertoires` M-QD repertoires (paper settings, one seed each; the paper uses
25 for the 2D tasks and 10 for the robot tasks), draw `--goals` goals
uniformly in the reachable part of the behavior box for each, and adapt toward
every goal with the three methods (Table II: step size 0.1, at most 10 steps).
Writes adaptation.json (per task, method and repertoire: mean error, mean
steps, fraction of goals within t_dist), adaptation.md (means +- std over
repertoires) and, with matplotlib, adaptation.png (bar charts as the paper's
Figures 3 and 4).
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import numpy as np
import report

import envs
from mqd_jax import Config, Task, adapt, run_mqd
from mqd_jax.adaptation import METHODS


def reachable_goals(task: Task, num: int, rng: np.random.Generator) -> np.ndarray:
    """[num, d] goals uniform in the reachable part of the behavior box (rejection sampling)."""
    low, high = np.asarray(task.behavior_low), np.asarray(task.behavior_high)
    goals = np.empty((0, len(low)), np.float32)
    while len(goals) < num:
        draw = rng.uniform(low, high, (2 * num, len(low))).astype(np.float32)
        goals = np.concatenate([goals, draw[task.reachable(draw)]])
    return goals[:num]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="*", default=["obstacle2d", "object2d"])
    parser.add_argument("--repertoires", type=int, default=25)
    parser.add_argument("--goals", type=int, default=1000)
    parser.add_argument("--generations", type=int, default=250)
    parser.add_argument("--out", default="results/adaptation")
    args = parser.parse_args()
    results: dict[str, dict[str, dict[str, list[float]]]] = {}
    for name in args.tasks:
        cfg = Config.paper_2d(task=name, algorithm="mqd", max_generations=args.generations)
        task = envs.make(name)
        keys = jax.random.split(jax.random.PRNGKey(0), args.repertoires)
        search = run_mqd.lower(keys[0], cfg).compile()
        results[name] = {m: {"error": [], "steps": [], "reached": []} for m in METHODS}
        for i, key in enumerate(keys):
            state, _ = search(key)
            goals = reachable_goals(task, args.goals, np.random.default_rng(i))
            for method in METHODS:
                out = adapt(state, goals, jax.random.fold_in(key, 1), cfg, method)
                r = results[name][method]
                r["error"].append(float(np.mean(out.errors)))
                r["steps"].append(float(np.mean(out.steps)))
                r["reached"].append(float(np.mean(np.asarray(out.errors) < cfg.t_dist)))
        print(name, {m: round(float(np.mean(v["error"])), 4) for m, v in results[name].items()}, flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "adaptation.json"), "w") as f:
        json.dump(results, f, indent=1)
    pm = lambda x: f"{np.mean(x):.4f} +- {np.std(x):.4f}"  # noqa: E731
    lines = [f"M-QD repertoires (paper 2D settings, {args.generations} generations), {args.repertoires} repertoires "
             f"x {args.goals} reachable goals per task; step size 0.1, at most 10 steps; {report.machine()}.", "",
             "| task | method | mean error | mean steps (= rollouts) | goals within t_dist |", "|---|---|---|---|---|"]
    for name, by_method in results.items():
        for method, r in by_method.items():
            lines.append(f"| {name} | {method} | {pm(r['error'])} | {np.mean(r['steps']):.2f} "
                         f"| {np.mean(r['reached']):.3f} |")
    report.write(lines, os.path.join(args.out, "adaptation.md"))
    _plot(results, os.path.join(args.out, "adaptation.png"))


def _plot(results: dict, path: str) -> None:
    plt = report.pyplot()
    if plt is None:
        return
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    width = 0.8 / len(METHODS)
    for ax, metric, label in zip(axes, ("error", "steps"), ("behavioral error", "adaptation steps"), strict=True):
        for j, method in enumerate(METHODS):
            means = [np.mean(results[t][method][metric]) for t in results]
            stds = [np.std(results[t][method][metric]) for t in results]
            ax.bar(np.arange(len(results)) + j * width, means, width, yerr=stds, label=method)
        ax.set_xticks(np.arange(len(results)) + width * (len(METHODS) - 1) / 2, list(results))
        ax.set_ylabel(label)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
