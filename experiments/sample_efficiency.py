"""Rollouts to QD: how many of QD's rollouts M-QD needs to reach QD's final coverage, per composition.

    python experiments/sample_efficiency.py [--tasks obstacle2d object2d] [--seeds 10]
        [--compositions qd mqd-paper mqd oracle] [--out docs/data/sample_efficiency_2d.md]
    python experiments/sample_efficiency.py --sweep DIR [DIR=SUFFIX ...] [--run COMPOSITION ...] [--out ...]
    python experiments/sample_efficiency.py --merge JSON[=TASK,...] [JSON ...] [--tasks ...] [--out ...]

A composition is a name of `COMPOSITIONS` (the presets and the oracle) or "NAME:OPTION=VALUE,..."
with options of the preset (`mqd:pool_factor=16`; refused before anything runs where the preset
has no such option, or the value is invalid). Every composition runs `--seeds`
seeds (`sweep.seed_keys`, the seeds `mqd sweep` uses) with the task's Table II settings, vmapped
in one batch (`sweep.run_batch`). `--sweep DIR ...` reads the
presets `mqd sweep` wrote to those folders instead of running (the robot tasks, whose runs take long);
`--run` adds compositions run here on the same tasks and seeds. `--merge` runs nothing: it writes one
table and figure of the curves in earlier outputs of this script (a composition in two files must
hold the same curve there, so every row is measured against one QD).

For each task and composition, from the mean over seeds of coverage [G] and rollouts spent [G]:
  * rollouts to QD: the rollouts at which the mean coverage first reaches QD's final mean
    coverage, as a fraction of QD's rollouts ("> x" if it never does: x = its own total), and
    its 90% percentile bootstrap interval over seeds (the mean curve crosses late, where it is
    flat, so this figure moves much more from seed to seed than the coverage does);
  * coverage after 25%, 50% and 100% of QD's rollouts (linear between generations);
  * mean quality and QD-score of the repertoire after QD's rollouts;
  * ms per generation (the batch's wall time after compiling, per generation) and its ratio to QD's
    in the same invocation (not with --sweep: its runs were timed in other processes).
The oracle ("oracle", 2D tasks only) is `mqd`'s acquisition fed the task's true outcomes instead of the model's
predictions: the ceiling of what a better model could buy ("oracle:noise=0.05": its behaviors off by a Gaussian
error of 0.05 per axis, a fixed function of the action: what a model of that error would buy). "local" is the preset
"mqd-local", `"mqd"` with the surrogate `LocalLinear` (`mqd_jax.surrogate.local`) in place of the network
("local:neighbours=32,buffer=2048": its options). "steer" is `"mqd"` whose `Steering` sets the share of its rows it
steers by adaptive pursuit (`Steering(share, pursuit=Fallback())`: more where steered rollouts open more niches than
the rest; "steer:steering_share=0.5": up to 45% of the pool, from 25%).

`--tasks arm`, `rugged_arm` and `rastrigin` are tasks none of this was tuned on (`extra_tasks.py`).

Writes a markdown table (`--out`), the mean curves as JSON beside it and a figure of coverage
against rollouts per task (`--figure`).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import os
import time
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import report
from extra_tasks import register_experiment_tasks

from mqd_jax import Config, Surrogate
from mqd_jax.core import algorithms, registry
from mqd_jax.core import repertoire as repertoire_lib
from mqd_jax.core.repertoire import Repertoire
from mqd_jax.core.task import Task
from mqd_jax.emitters.pursuit import Fallback
from mqd_jax.experiment import results, stats
from mqd_jax.experiment.progress import Progress
from mqd_jax.experiment.sweep import run_batch, seed_keys
from mqd_jax.surrogate.surrogate import SurrogateState


@dataclasses.dataclass(frozen=True)
class Oracle(Surrogate):
    """A surrogate whose "members" are the task's true outcomes (one member; NaN where invalid).

    For deterministic tasks with cheap rollouts only: it rolls out its whole pool inside the
    generation to judge it, so it is a reference, not a method. With `noise` > 0 each behavior it gives is off by
    a Gaussian error of that standard deviation per axis (behavior units), a fixed function of the action (the same
    action, the same error): a model that errs by that much, how many rollouts it would need."""

    noise: float = 0.0

    def members(self, state: SurrogateState, actions: jax.Array, task: Task,
                inputs: jax.Array | None = None) -> jax.Array:
        behaviors, qualities, valid = task.evaluate(actions, jax.random.PRNGKey(0))
        if self.noise:
            bits = jax.lax.bitcast_convert_type(jax.lax.stop_gradient(actions).astype(jnp.float32), jnp.uint32)
            odd = jnp.arange(actions.shape[1], dtype=jnp.uint32) * 2 + 1
            seeds = (bits * odd * jnp.uint32(2654435761)).sum(axis=1)  # a hash of the action's bits
            error = jax.vmap(lambda s: jax.random.normal(jax.random.PRNGKey(s), (behaviors.shape[1],)))(seeds)
            behaviors = behaviors + self.noise * error
        outcome = jnp.concatenate([behaviors, qualities[:, None]], axis=-1).astype(jnp.float32)
        return jnp.where(valid[:, None], outcome, jnp.nan)[None]


# The compositions the report's tables still show: the presets and the oracle. The compositions that stood for
# earlier versions of "mqd" and the ablations measured on the way (docs/results.md's history) are in the git
# history: commit 7e79d7f holds this script with all of them.
COMPOSITIONS = ("qd", "mqd-paper", "mqd", "random", "oracle", "local", "steer")
FRACTIONS = (0.25, 0.5, 1.0)


def warmup(cfg: Config) -> int:
    """The rollouts before a config's model is used (0 without a model)."""
    return getattr(cfg.emitter, "warmup_samples", 0)


def configured(spec: str, task: str, generations: int | None = None) -> Config:
    """The config a composition spec runs on `task` with Table II's settings: "NAME" (of `COMPOSITIONS`) or
    "NAME:OPTION=VALUE,..." (options of the preset, `mqd_jax.emitters.presets`, the oracle taking "mqd"'s, or fields
    of the `Config` such as `capacity`). Refused (SystemExit) for an unknown name or option and for an invalid
    value."""
    name, _, changes = spec.partition(":")
    if name not in COMPOSITIONS:
        raise SystemExit(f"{spec!r}: {name!r} is not a composition ({', '.join(COMPOSITIONS)})")
    preset = {"oracle": "mqd", "local": "mqd-local", "steer": "mqd"}.get(name, name)
    options = {}
    for change in filter(None, changes.split(",")):
        option, equals, text = change.partition("=")
        if not equals:
            raise SystemExit(f"{spec!r}: {change!r} is not OPTION=VALUE")
        try:
            options[option] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            options[option] = text
    fields = {f.name for f in dataclasses.fields(Config)} - {"algorithm", "algorithm_options", "task"}
    changed = {field: options.pop(field) for field in fields & set(options)}
    noise = options.pop("noise", 0.0) if name == "oracle" else 0.0
    length = {} if generations is None else {"max_generations": generations}
    try:
        cfg = Config.paper(task, algorithm=preset, algorithm_options=options, **{**length, **changed})
        if name == "oracle":  # the preset's acquisition fed the true outcomes
            oracle = dataclasses.replace(cfg.emitter, surrogate=Oracle(num_batches=1, noise=float(noise)),
                                         parts=tuple(p for p in cfg.emitter.parts if p.name != "fallback"))
            cfg = dataclasses.replace(cfg, algorithm=oracle, algorithm_options={})
        if name == "steer":  # the share of the steering rows steered, by adaptive pursuit
            chain = tuple(dataclasses.replace(p, pursuit=Fallback()) if p.name == "steering" else p
                          for p in cfg.emitter.parts)
            cfg = dataclasses.replace(cfg, algorithm=dataclasses.replace(cfg.emitter, parts=chain),
                                      algorithm_options={})
    except ValueError as error:
        raise SystemExit(f"{spec!r}: {error}") from None
    return cfg


# Each seed's final repertoire of a run made here: not written to the JSON (large).
SKILLS = "final_skills"


class Compiled(Progress):
    """Remembers when the batch's program was compiled (`at`, perf_counter seconds)."""

    def compiled(self) -> None:
        self.at = time.perf_counter()


def _run(task: str, spec: str, seeds: int, generations: int | None) -> dict[str, Any]:
    cfg = configured(spec, task, generations)
    compiled = Compiled()
    start = time.perf_counter()
    states, metrics = run_batch(cfg, seed_keys(seeds), progress=compiled)
    ms = (time.perf_counter() - compiled.at) / cfg.max_generations * 1e3
    print(f"{task} {spec}: {time.perf_counter() - start:.0f} s", flush=True)
    skills = [jax.tree.map(lambda x, i=i: x[i], states.repertoire) for i in range(seeds)]
    return _curves(metrics, warmup(cfg)) | {"ms_per_generation": ms, SKILLS: skills, "t_dist": cfg.t_dist}


def quality_on_shared_niches(skills: list[Repertoire], qd_skills: list[Repertoire],
                             t_dist: float) -> tuple[float, float]:
    """The mean over seeds of the mean quality difference, over QD's final skills that have one of the
    composition's (same seed) within `t_dist`, of the nearest such skill's quality minus QD's; and the mean share
    of QD's skills that have one. A mean quality compares repertoires of different niches (one that holds more far,
    hard niches scores lower with skills as good where both hold one); this compares like with like."""
    gaps, shares = [], []
    for rep, qd in zip(skills, qd_skills, strict=True):
        qd_b, qd_q = np.asarray(qd.behaviors[:qd.count]), np.asarray(qd.qualities[:qd.count])
        sq_distance, slot = repertoire_lib.nearest(rep, rep.behaviors, qd_b)  # inf where rep is empty
        shared = np.asarray(sq_distance) <= t_dist ** 2
        gaps.append(np.mean(np.asarray(rep.qualities)[np.asarray(slot)[shared]] - qd_q[shared])
                    if shared.any() else np.nan)
        shares.append(shared.mean() if len(qd_b) else 0.0)
    with warnings.catch_warnings():  # no seed with a shared niche: NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        return float(np.nanmean(gaps)), float(np.mean(shares))


# The model's diagnostics (README, "Metrics"), averaged over seeds and the generations past warm-up.
DIAGNOSTICS = ("opener_auc", "model_share", "steered", "steering_share", "validity_auc", "prediction_error")


def _curves(metrics: dict[str, np.ndarray], warmup_samples: int) -> dict[str, Any]:
    """Mean curves over seeds, each seed's rollouts and coverage curves [S, G] and final coverage, the share of all
    rollouts that were invalid, and the mean of each model diagnostic the run has over the generations that began
    with `warmup_samples` rollouts or more (NaN if none)."""
    evaluations = np.asarray(metrics["num_evaluations"], float)
    trained = np.pad(evaluations[:, :-1], ((0, 0), (1, 0))) >= warmup_samples  # [S, G]
    with warnings.catch_warnings():  # a run that never left warm-up averages to NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        diagnostics = {name: float(np.nanmean(np.where(trained, np.asarray(metrics[name], float), np.nan)))
                       for name in DIAGNOSTICS if name in metrics}
    return {"rollouts": np.mean(metrics["num_evaluations"], 0).tolist(),
            "seed_rollouts": np.asarray(metrics["num_evaluations"], float).tolist(),
            # Rounded to 1e-6 (a cell of the coverage grid is 1.5e-5): the JSON stays a third of its size.
            "seed_coverage": np.round(np.asarray(metrics["coverage"], float), 6).tolist(),
            "coverage": np.mean(metrics["coverage"], 0).tolist(),
            "mean_quality": np.mean(metrics["mean_quality"], 0).tolist(),
            **({"qd_score": np.mean(metrics["qd_score"], 0).tolist()} if "qd_score" in metrics else {}),
            "final_coverage": np.asarray(metrics["coverage"])[:, -1].tolist(),
            "invalid_share": float(np.sum(metrics["invalid"]) / np.sum(metrics["evaluations"]))
            if "invalid" in metrics else float("nan"), **diagnostics}


def rollouts_to_reach(rollouts: np.ndarray, coverage: np.ndarray, target: float) -> float | None:
    """The rollouts [G] at the first generation whose coverage [G] reaches `target`, or None."""
    reached = np.asarray(coverage) >= target
    return float(np.asarray(rollouts)[np.argmax(reached)]) if reached.any() else None


def rollouts_to_qd_interval(curve: dict[str, Any], qd: dict[str, Any],
                            level: float = 0.9) -> tuple[float, float] | None:
    """The percentile bootstrap interval (`stats.bootstrap_interval`, seeds resampled) of rollouts to QD as a
    fraction of QD's rollouts (inf for a resample that never reaches QD's final coverage); QD's seeds are resampled
    too where its curve has them, else its mean curve is held fixed. None without the composition's per-seed
    curves (files written before them)."""
    if "seed_coverage" not in curve:
        return None

    def seeds(c: dict[str, Any]) -> np.ndarray:
        """[S, 2, G]: each seed's rollouts and coverage, resampled together."""
        return np.stack([np.asarray(c["seed_rollouts"]), np.asarray(c["seed_coverage"])], axis=1)

    def to_qd(runs: np.ndarray, qd_runs: np.ndarray | None = None) -> float:
        qd_mean = np.asarray([qd["rollouts"], qd["coverage"]]) if qd_runs is None else qd_runs.mean(0)
        mean = runs.mean(0)
        reach = rollouts_to_reach(mean[0], mean[1], qd_mean[1, -1])
        return np.inf if reach is None else reach / qd_mean[0, -1]

    return stats.bootstrap_interval(to_qd, [seeds(curve), *([seeds(qd)] if "seed_coverage" in qd else [])], level)


def _interval_text(interval: tuple[float, float] | None) -> str:
    if interval is None:
        return ""
    return " - ".join(f"{end:.2f}" if np.isfinite(end) else "never" for end in interval)


def _row(name: str, curve: dict[str, Any], qd: dict[str, Any], timed: bool) -> list[str]:
    budget, target = qd["rollouts"][-1], qd["coverage"][-1]
    reach = rollouts_to_reach(curve["rollouts"], curve["coverage"], target)
    to_qd = f"{reach / budget:.2f}" if reach is not None else f"> {curve['rollouts'][-1] / budget:.2f}"
    at = [f"{np.interp(f * budget, curve['rollouts'], curve['coverage']):.3f}"
          + ("*" if f * budget > curve["rollouts"][-1] + 0.5 else "") for f in FRACTIONS]
    quality = np.interp(budget, curve["rollouts"], curve["mean_quality"])
    qd_score = f"{np.interp(budget, curve['rollouts'], curve['qd_score']):.1f}" if "qd_score" in curve else ""
    final = np.asarray(curve["final_coverage"])
    timing = [f"{curve['ms_per_generation']:.1f}", f"{curve['ms_per_generation'] / qd['ms_per_generation']:.2f}"] \
        if timed else ["", ""]
    diagnostics = [(f"{curve[n]:.5f}" if n == "prediction_error" else f"{curve[n]:.2f}")
                   if np.isfinite(curve.get(n, np.nan)) else "" for n in ("invalid_share", *DIAGNOSTICS)]
    # Final repertoires compare at QD's budget only where both runs spent it.
    shared = ""
    if SKILLS in curve and SKILLS in qd and abs(curve["rollouts"][-1] - budget) < 0.5:
        gap, share = quality_on_shared_niches(curve[SKILLS], qd[SKILLS], curve["t_dist"])
        shared = f"{gap:+.3f} ({share:.2f})"
    return [name, to_qd, _interval_text(rollouts_to_qd_interval(curve, qd)), *at, f"{quality:.3f}", qd_score, shared,
            f"{final.mean():.3f} +- {final.std():.3f}",
            f"{curve['rollouts'][-1]:.0f}", *timing, *diagnostics]


def _figure(curves: dict[str, dict[str, dict[str, Any]]], path: str) -> str | None:
    """Draws the curves to `path` and returns it; None without matplotlib (`report.pyplot` says so)."""
    plt = report.pyplot()
    if plt is None:
        return None
    columns = min(4, len(curves))  # rows of at most four tasks
    rows = -(-len(curves) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.6 * rows), squeeze=False)
    # One colour per composition in every panel, in the order the compositions first appear.
    names = list(dict.fromkeys(name for by in curves.values() for name in by))
    colours = {name: f"C{i % 10}" for i, name in enumerate(names)}
    handles = {}  # a line of each composition, for one legend of all of them (some panels lack some)
    for ax, (task, by) in zip(axes.flat, curves.items(), strict=False):  # spare panels stay blank
        for name, c in by.items():
            handles[name], = ax.plot(c["rollouts"], c["coverage"], color=colours[name],
                                     lw=2.2 if name == "mqd" else 1.2,
                                     ls="--" if name.partition(":")[0] == "oracle" else "-")
        ax.axhline(by["qd"]["coverage"][-1], color="0.6", lw=0.8, ls=":")
        ax.set(title=task, xlabel="rollouts", ylabel="coverage")
    for ax in axes.flat[len(curves):]:
        ax.axis("off")
    axes.flat[len(curves) - 1].legend([handles[n] for n in names], names, fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def figure_path(out: str) -> str:
    """The figure beside the table `out`: docs/data/NAME.md -> docs/figures/NAME.png, else NAME.png in out's folder
    (so a table written elsewhere never overwrites a figure in docs)."""
    folder, name = os.path.split(os.path.splitext(out)[0])
    if os.path.normpath(folder) == os.path.join("docs", "data"):
        folder = os.path.join("docs", "figures")
    return os.path.join(folder, name + ".png")


def _preset_name(algorithm: str, cfg: Config) -> str:
    """A sweep's preset as a composition's name, its options other than the defaults (and Table II's) named."""
    column = registry.make(cfg.task_name).table_ii_column if isinstance(cfg.task, str) else "2d"
    table = algorithms.table_ii(algorithm, column)
    changed = {o: v for o, v in cfg.algorithm_options if table.get(o) != v}
    return algorithm + ("" if not changed else ":" + ",".join(f"{o}={v}" for o, v in changed.items()))


def _baselines(paths: list[str], tasks: list[str], seeds: int, generations: int | None) -> dict[str, dict[str, Any]]:
    """task -> {"qd": curve} from earlier outputs (JSON) of this script, refused before anything runs where a task's
    QD curve stands in two of them or was run with other seeds or generations than asked."""
    known: dict[str, dict[str, Any]] = {}
    for path in paths:
        with open(path) as f:
            for task, by in json.load(f).items():
                if task not in tasks or "qd" not in by:
                    continue
                if task in known:
                    raise SystemExit(f"--baseline: QD's curve of {task} stands in two files; name one")
                qd = by["qd"]
                expected = generations or Config.paper(task).max_generations
                if len(qd["final_coverage"]) != seeds or len(qd["rollouts"]) != expected:
                    raise SystemExit(f"--baseline {path}: QD's {task} curve has {len(qd['final_coverage'])} seeds and "
                                     f"{len(qd['rollouts'])} generations, not the {seeds} and {expected} asked")
                known[task] = {"qd": qd}
    return known


def merged(paths: list[str], tasks: list[str] | None) -> dict[str, dict[str, dict[str, Any]]]:
    """task -> composition -> curve from earlier outputs (JSON) of this script, in the files' order ("PATH=TASK,TASK":
    only those tasks of that file), of `tasks` only where given (in their order; refused where no file holds one).
    Refused (SystemExit) where a composition's curve of a task stands in two files and differs: two draws of QD's
    runs would measure rows against different baselines."""
    curves: dict[str, dict[str, dict[str, Any]]] = {}
    for spec in paths:
        path, _, only = spec.partition("=")
        with open(path) as f:
            for task, by in json.load(f).items():
                if (tasks is not None and task not in tasks) or (only and task not in only.split(",")):
                    continue
                for name, curve in by.items():
                    held = curves.setdefault(task, {}).setdefault(name, curve)
                    if any(held.get(key) != curve.get(key) for key in ("rollouts", "coverage", "mean_quality")):
                        raise SystemExit(f"--merge {path}: {task}'s {name} differs from its curve in an earlier file")
    if tasks is None:
        return curves
    missing = [task for task in tasks if task not in curves]
    if missing:
        raise SystemExit(f"--merge: no file holds {', '.join(missing)}")
    return {task: curves[task] for task in tasks}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=None,
                        help="default: obstacle2d object2d; with --merge, every task of the files")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--generations", type=int, default=None, help="override Table II's (quick checks)")
    parser.add_argument("--compositions", nargs="+", default=["qd", "mqd-paper", "mqd", "oracle"],
                        help="names of COMPOSITIONS, each optionally with the preset's options or Config fields "
                             "changed: NAME:OPTION=VALUE,...")
    parser.add_argument("--sweep", nargs="+", default=None,
                        help="read the presets of `mqd sweep` folders instead of running; DIR=SUFFIX names "
                        "that folder's runs PRESET-SUFFIX (a variant beside the same presets in another folder)")
    parser.add_argument("--run", nargs="+", default=None,
                        help="with --sweep: also run these compositions (as --compositions) on the sweeps' tasks and "
                        "seeds")
    parser.add_argument("--baseline", nargs="+", default=[], metavar="JSON",
                        help="take QD's curves (which no model change touches) from these earlier outputs of this "
                        "script (NAME.json beside NAME.md, which names its machine and seeds) instead of running QD; "
                        "on a contact task a file from an earlier version may hold another draw of QD's runs "
                        "(docs/results.md, 'Quality on QD's niches')")
    parser.add_argument("--merge", nargs="+", default=None, metavar="JSON[=TASK,...]",
                        help="run nothing: tabulate and draw the curves of these earlier outputs of this script "
                        "together, JSON=TASK,TASK taking only those tasks of a file (timings and quality on QD's "
                        "niches blank: they need runs made here)")
    parser.add_argument("--out", default="docs/data/sample_efficiency_2d.md")
    parser.add_argument("--figure", default=None,
                        help="default: docs/figures/NAME.png for --out docs/data/NAME.md, else NAME.png beside --out")
    args = parser.parse_args()
    tasks = args.tasks or ["obstacle2d", "object2d"]  # the tasks to run; --merge reads args.tasks itself
    register_experiment_tasks(tasks)
    for task in [] if args.merge else tasks:  # a bad spec is refused before anything runs
        for spec in [*args.compositions, *(args.run or [])]:
            configured(spec, task)

    curves: dict[str, dict[str, dict[str, Any]]] = {}
    if args.baseline and args.sweep:
        raise SystemExit("--baseline is for runs made here; with --sweep QD's curves come from the sweep")
    if args.merge and (args.sweep or args.baseline or args.run):
        raise SystemExit("--merge runs nothing: it takes no --sweep, --baseline or --run")
    known = _baselines(args.baseline, tasks, args.seeds, args.generations)
    if args.merge:
        curves = merged(args.merge, args.tasks)
        seeds = {len(c["final_coverage"]) for by in curves.values() for c in by.values()}
        command = (f"python experiments/sample_efficiency.py --merge {' '.join(args.merge)}"
                   + (f" --tasks {' '.join(args.tasks)}" if args.tasks else ""))
    elif args.sweep:
        folders = [spec.partition("=") for spec in args.sweep]
        loaded = [results.load_runs(folder) for folder, _, _ in folders]
        for (_, _, suffix), runs in zip(folders, loaded, strict=True):
            for task, by in runs.items():
                curves.setdefault(task, {}).update(
                    {_preset_name(alg, r.cfg) + (f"-{suffix}" if suffix else ""):
                     _curves(r.metrics, warmup(r.cfg)) for alg, r in by.items()})
        seeds = {len(r.keys) for runs in loaded for by in runs.values() for r in by.values()}
        command = f"python experiments/sample_efficiency.py --sweep {' '.join(args.sweep)}"
        if args.run:  # beside the sweeps' runs, on their tasks and seeds (`mqd sweep` runs sweep.seed_keys too)
            if len(seeds) != 1:
                raise SystemExit(f"--run needs sweeps of one number of seeds, not {sorted(seeds)}")
            for task, by in curves.items():
                by.update({name: _run(task, name, next(iter(seeds)), args.generations) for name in args.run})
            command += f" --run {' '.join(args.run)}"
    else:
        for task in tasks:
            robot = registry.make(task).table_ii_column == "robot"
            names = ["qd"] + [n for n in args.compositions
                              if n != "qd" and not (robot and n.partition(":")[0] == "oracle")]
            curves[task] = {name: known[task][name] if name in known.get(task, {}) else
                            _run(task, name, args.seeds, args.generations) for name in names}
        seeds = {args.seeds}
        command = (f"python experiments/sample_efficiency.py --tasks {' '.join(tasks)} --seeds {args.seeds} "
                   f"--compositions {' '.join(args.compositions)}"
                   + (f" --generations {args.generations}" if args.generations else "")
                   + (f" --baseline {' '.join(args.baseline)}" if args.baseline else ""))
    missing = [t for t, by in curves.items() if "qd" not in by]
    if missing:
        raise SystemExit(f"no QD runs of {missing}: rollouts to QD needs them")

    taken = sorted({n for task, by in curves.items() for n in by if n in known.get(task, {})})
    made = (f"Runs from {', '.join(args.merge)} (each .md beside them names its machine and seeds); seeds per run: "
            f"{sorted(seeds)}." if args.merge else f"Machine: {report.machine()}; seeds: {sorted(seeds)}.")
    lines = [f"Command: `{command}`", "", made
             + (f" {', '.join(taken)}: from {', '.join(args.baseline)} (not run here; the machine and seeds are "
                "in the .md beside it)." if taken else ""), "",
             "Rollouts to QD = fraction of QD's rollouts at which the mean coverage first reaches QD's final mean "
             "coverage; its 90% interval: a percentile bootstrap over seeds (2000 resamples of the composition's "
             "seeds and of QD's; QD's mean held fixed where its per-seed curves are not in its file; blank for "
             "curves from files written before per-seed curves; \"never\": resamples that never reach it). "
             "Coverage at 25/50/100% of QD's rollouts (* = the composition spent fewer in all: its "
             "final value). Quality = the repertoire's mean quality after QD's rollouts; QD-score = the sum over "
             "its skills of quality minus the task's lowest quality (`quality_range`), after QD's rollouts (blank "
             "in files written before it). Quality on QD's niches: "
             "over QD's final skills with one of the composition's final skills within t_dist (same seed; the share "
             "of QD's skills that have one in brackets), the mean of the nearest such skill's quality minus QD's; "
             "blank where QD ran in another process or the composition spent other rollouts than QD."
             + ("" if args.sweep or args.merge else " ms/gen: the batch's time per generation after compiling; ratio "
                "to QD's (blank where QD's curve was not run here).")
             + " Invalid: the share of all rollouts that were invalid (blank in files written before it)."
             " Opener AUC, model share, steered, steering share, validity AUC, held-out error: the model's "
             "diagnostics `opener_auc`, `model_share`, `steered` (rollouts per generation), `steering_share`, "
             "`validity_auc` and `prediction_error` (the behavior MSE of its predictions of each generation's "
             "rollouts, before it trains on them) (README, \"Metrics\"; AUC 0.5 = chance), averaged over seeds and "
             "the generations past warm-up.",
             ""]
    header = ["composition", "rollouts to QD", "90% interval", "cov @25%", "cov @50%", "cov @100%", "quality",
              "QD-score", "quality on QD's niches", "final coverage",
              "rollouts", "ms/gen", "x QD", "invalid", "opener AUC", "model share", "steered", "steering share",
              "validity AUC", "held-out error"]
    for task, by in curves.items():
        lines += [f"### {task}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        # Times are ratios within one invocation: none where QD's curve came from another.
        timed = not (args.sweep or args.merge) and "qd" not in known.get(task, {})
        lines += ["| " + " | ".join(_row(n, c, by["qd"], timed)) + " |" for n, c in by.items()]
        lines.append("")
    report.write(lines, args.out)
    with open(os.path.splitext(args.out)[0] + ".json", "w") as f:
        json.dump({task: {name: {k: v for k, v in c.items() if k != SKILLS} for name, c in by.items()}
                   for task, by in curves.items()}, f)
    figure = _figure(curves, args.figure or figure_path(args.out))
    if figure:
        print(figure)


if __name__ == "__main__":
    main()
