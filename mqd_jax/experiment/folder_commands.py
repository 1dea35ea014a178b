"""The commands that read a results folder: `mqd adapt` (a sweep's M-QD repertoires toward random goals), `mqd
plot` (a sweep's tables and figures) and `mqd render` (a skill of a run as an animated GIF)."""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import time

import jax
import numpy as np

from mqd_jax import adaptation
from mqd_jax.core.state import get_task
from mqd_jax.experiment import files, folders, manifest, messages, migrations, plots, results, tables
from mqd_jax.experiment import progress as progress_lib
from mqd_jax.experiment.messages import count_of, say_removed
from mqd_jax.experiment.provenance import provenance


def adapt(args: argparse.Namespace) -> None:
    path = os.path.join(args.dir, results.ADAPTATION)
    with folders.lock(args.dir, create=False) as leftovers:
        say_removed(leftovers, "left by an interrupted writer")
        _sweep_folder(args.dir, "adapt")
        try:
            found = results.read_adaptation(args.dir)
        except files.Damaged as e:
            if args.tasks:
                raise ValueError(f"{e} (it holds the other tasks' results)") from e
            kept = files.set_aside([e.path])
            print(f"{e}\nwritten anew with every task; the damaged file is kept as {kept[0]}")
            found = {}
        tasks = args.tasks or [t for t, by in results.load_runs(args.dir).items() if "mqd" in by]
        if not tasks:
            raise ValueError(f"{args.dir!r} holds no M-QD runs to adapt: run "
                             f"`{messages.command('mqd', 'sweep', '--algorithms', 'mqd', ('--out', args.dir))}` first")
        steps = progress_lib.Steps("adapt", len(tasks) * len(adaptation.METHODS), "method")
        for task in tasks:
            cfg, keys, states = results.load_states(args.dir, task)
            goals = np.stack([adaptation.reachable_goals(get_task(cfg), args.goals, np.random.default_rng(i))
                              for i in range(len(keys))])
            rollout_keys = jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys)
            methods = {}
            for method in adaptation.METHODS:
                start = time.perf_counter()
                out = jax.device_get(adaptation.adapt_batch(states, goals, rollout_keys, cfg, method,
                                                            args.step_size, args.steps))
                methods[method] = {"error": out.errors.mean(1), "steps": out.steps.mean(1),
                                   "reached": (out.errors < cfg.t_dist).mean(1), "goals": args.goals,
                                   "wall_s": time.perf_counter() - start}
                steps.step(f"{task} {method}: mean error {out.errors.mean():.4f}, mean steps "
                           f"{out.steps.mean():.2f}, {methods[method]['wall_s']:.1f} s", f"{task} {method}")
            found[task] = {"source": results.source(args.dir, task), "config": cfg.to_dict(),
                           "step_size": args.step_size, "steps": args.steps, "keys": keys,
                           "provenance": provenance(), "methods": methods}
            results.remove_derived(args.dir)
            folders.write_json(path, found)
        steps.close()
        tabulate(args.dir, show="adaptation.md")


def _sweep_folder(folder: str, command: str) -> None:
    """Refuses (ValueError) a folder that `mqd run` wrote: `command` works on a sweep's folder."""
    if manifest.kind(folder) == "run":
        raise ValueError(f"{folder!r} is a folder of `mqd run`: `mqd {command}` takes a folder of `mqd sweep` (a "
                         "run's folder holds its figure, run.png; `mqd render` watches its skills)")


def tabulate(out: str, pair: tuple[int, int] | None = None, show: str | None = None) -> None:
    """Tables (markdown) and figures of everything in the results folder `out` (call holding its lock); `pair`:
    the two behavior dimensions (0-based) Figure 2 shows of each task that has them (refused if none has); `show`:
    print only this table (default: every one)."""
    runs = results.load_runs(out)
    dims = {task: get_task(next(iter(by_alg.values())).cfg).behavior_dim for task, by_alg in runs.items()}
    if pair is not None and not any(max(pair) < d for d in dims.values()):  # before anything is written
        plots.projections(max(dims.values()), pair)  # raises, naming the dimensions
    results.remove_derived(out)
    tables.write_markdown(tables.table_one(runs, results.missing(out)), os.path.join(out, "table1.md"),
                           show in (None, "table1.md"))
    for task, by_alg in runs.items():
        plots.figure2(get_task(next(iter(by_alg.values())).cfg), task, by_alg,
                      os.path.join(out, f"fig2_{results.file_name(task)}.png"),
                      pair if pair is not None and max(pair) < dims[task] else None)
    try:
        found, stale = results.adaptation(out)
    except files.Damaged as e:
        print(f"left out the adaptation results: {e}")
        found, stale = {}, []
    if stale:
        print(f"left out the adaptation results of {', '.join(stale)}: their M-QD runs changed since `mqd adapt`; "
              f"run `mqd adapt {out} --tasks {' '.join(stale)}` again")
    if found:
        tables.write_markdown(tables.adaptation_table(found), os.path.join(out, "adaptation.md"),
                               show in (None, "adaptation.md"))
        plots.adaptation_figure(found, "error", "behavioral error", os.path.join(out, "fig3_adaptation_error.png"))
        plots.adaptation_figure(found, "steps", "adaptation steps", os.path.join(out, "fig4_adaptation_steps.png"))


def _rounded(values: np.ndarray) -> list[float]:
    """values as Python floats rounded to 3 decimals (float32's binary noise gone: 0.199, not 0.19900000095)."""
    return [round(float(v), 3) for v in np.asarray(values, np.float64)]


def render(args: argparse.Namespace) -> None:
    """A skill of a `mqd run` folder as an animated GIF: the robot executing it, or a 2D task's behavior path."""
    # Offscreen OpenGL for MuJoCo's renderer unless the user chose a platform (read when mujoco is imported).
    os.environ.setdefault("MUJOCO_GL", "egl")
    if not os.path.isdir(args.dir):
        raise ValueError(f"{args.dir!r} does not exist: give the folder a `mqd run` wrote")
    if manifest.kind(args.dir) == "sweep":
        raise ValueError(f"{args.dir!r} is a folder of `mqd sweep`: `mqd render` takes a folder of `mqd run` "
                         f"(`{messages.command('mqd', 'plot', args.dir)}` draws a sweep's repertoires)")
    paths = [os.path.join(args.dir, f) for f in ("metrics.json", "repertoire.npz")]
    missing = [f for f in paths if not os.path.lexists(f)]
    if missing:
        raise ValueError(f"{missing[0]!r} is missing: {args.dir!r} is not a whole folder of `mqd run` (metrics.json, "
                         "repertoire.npz)")
    resume = messages.command("mqd", "run", "--resume", ("--out", args.dir))
    repair = f"the `mqd run` that made it, `{resume}`, writes it again from its checkpoint"
    saved = files.read_json(paths[0], repair)
    if not isinstance(saved.get("config"), dict):
        raise ValueError(f"{args.dir!r} is not a folder of `mqd run` (no config in metrics.json): {repair}")
    try:
        cfg = migrations.config_from(saved["config"])
    except (TypeError, ValueError) as e:
        raise files.Damaged(paths[0], f"holds an invalid config ({e})", repair) from None
    arrays = files.read_npz(paths[1], repair, results.npz_bytes(cfg))
    if not {"actions", "behaviors"} <= set(arrays):
        raise ValueError(f"{args.dir!r} is not a folder of `mqd run` (no actions or behaviors): {repair}")
    actions, behaviors = arrays["actions"], arrays["behaviors"]
    if len(actions) == 0:
        raise ValueError(f"{paths[1]!r} holds no skills (the run inserted none): there is nothing to render")
    if args.goal is not None and not all(math.isfinite(g) for g in args.goal):
        raise ValueError(f"--goal {' '.join(map(str, args.goal))} is invalid: expected finite numbers")
    if args.goal is not None and len(args.goal) != behaviors.shape[1]:
        raise ValueError(f"--goal {' '.join(map(str, args.goal))} has {len(args.goal)} numbers: the task's behaviors "
                         f"have {behaviors.shape[1]}")
    if args.goal is not None:
        index = int(np.argmin(np.linalg.norm(behaviors - np.asarray(args.goal), axis=1)))
    elif 0 <= args.index < len(actions):
        index = args.index
    else:
        raise ValueError(f"--index {args.index}: the repertoire holds {count_of(len(actions), 'skill')} (0 to "
                         f"{len(actions) - 1})")
    out = args.out or os.path.join(args.dir, f"skill_{index}.gif")
    target = os.path.dirname(out) or "."
    if not out.lower().endswith(".gif") or not os.path.isdir(target):
        raise ValueError(f"--out {out!r} is invalid: expected a new .gif file in an existing folder")
    ours = manifest.kind(target) is not None  # a results folder: its lock, and only files its manifest lists
    if not ours and os.path.lexists(out):
        raise ValueError(f"--out {out!r} exists: `mqd render` replaces only a GIF it wrote in a results folder; "
                         "remove it, or give another --out")
    print(f"skill {index}: behavior {_rounded(behaviors[index])}, action {_rounded(actions[index])}")
    with folders.lock(target, create=False) if ours else contextlib.nullcontext():
        if ours and files.lexists(out) and os.path.basename(out) not in manifest.written(target):
            raise ValueError(f"--out {out!r} is not written by mqd-jax there (not in its manifest), so it is not "
                             "replaced: remove it, or give another --out")
        try:
            frames = get_task(cfg).frames(actions[index], args.width, args.height)
        except NotImplementedError as e:
            raise ValueError(str(e)) from e
        except Exception as e:  # MuJoCo's OpenGL context: say how to get one offscreen
            if "gl" not in str(e).lower():
                raise
            raise ValueError(f"cannot render ({type(e).__name__}: {e}); offscreen: set MUJOCO_GL=egl (or osmesa)"
                             ) from e
        plots.write_animation(frames, out)


def plot(args: argparse.Namespace) -> None:
    pair = None if args.pair is None else (args.pair[0] - 1, args.pair[1] - 1)
    with folders.lock(args.dir, create=False) as leftovers:
        say_removed(leftovers, "left by an interrupted writer")
        _sweep_folder(args.dir, "plot")
        tabulate(args.dir, pair)

