"""Figures (matplotlib, the optional `plot` extra): a run, Figure 2, and Figures 3-4.

A run's figure (`run_figure`, `of_state` for a state and its metrics, `run_fig` for the figure itself) shows
coverage, QD-score and max and mean quality against rollouts, and the final repertoire coloured by quality with
a colour bar (each pairwise projection for more than two behavior dimensions, over the task's layout where it
has one); Figure 2 (`figure2`) the same per algorithm over a sweep's seeds, with their spread.

Every function writes one PNG and returns its path, or returns None (saying
so) when matplotlib is not installed: results files never depend on it.
"""

from __future__ import annotations

import io
import json
from typing import Any

import jax
import numpy as np

from mqd_jax.adaptation import METHODS
from mqd_jax.core.task import Task
from mqd_jax.experiment.folders import write_atomically
from mqd_jax.experiment.provenance import provenance
from mqd_jax.experiment.results import Runs
from mqd_jax.experiment.tables import NAMES


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (a notebook's inline backend kept: its figures show in the cells), or
    None (with a message) when matplotlib is not installed."""
    try:
        import matplotlib

        if "inline" not in matplotlib.get_backend():
            matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed (pip install -e .[plot]): no figure written")
        return None
    return plt


def save(fig: Any, path: str, description: str | None = None) -> str:
    """Writes `fig` to `path` atomically (PNG, 100 dpi; `description`, by default mqd-jax's provenance as JSON, goes
    into the PNG's Description text: what proves the figure mqd-jax's) and says so."""
    fig.tight_layout()
    buffer = io.BytesIO()
    description = description or json.dumps({"provenance": provenance()})
    fig.savefig(buffer, format="png", dpi=100, metadata={"Description": description})
    write_atomically(path, buffer.getvalue())
    pyplot().close(fig)  # pyplot keeps every open figure alive: a long sweep would hold them all
    print(f"wrote {path}")
    return path


def layout(ax: Any, task: Task) -> None:
    """Draws `task.layout()` on the axes `ax`, each label once in the legend."""
    from matplotlib.patches import Ellipse, Rectangle

    labelled: set[str] = set()
    for region in task.layout():
        (x0, y0), (x1, y1) = region.low, region.high
        label = None if region.label in labelled else region.label
        labelled.add(region.label)
        style = (dict(color=region.colour or "0.6", alpha=0.7, label=label) if region.filled
                 else dict(fill=False, ls="--", label=label))
        patch = Ellipse(((x0 + x1) / 2, (y0 + y1) / 2), x1 - x0, y1 - y0, **style) if region.shape == "disk" \
            else Rectangle((x0, y0), x1 - x0, y1 - y0, **style)
        ax.add_patch(patch)


def projections(dims: int, pair: tuple[int, int] | None = None) -> list[tuple[int, int]]:
    """The behavior dimensions (0-based) each repertoire panel shows: [(0, 0)] for one dimension (a strip),
    [(0, 1)] for two, every pair i < j for more (their pairwise 2-D projections), or only `pair`. Raises
    ValueError for a pair outside the dimensions."""
    if pair is not None:
        i, j = pair
        if not (0 <= i < dims and 0 <= j < dims and i != j):
            raise ValueError(f"--pair {i + 1} {j + 1} is invalid: expected two different behavior dimensions of "
                             f"1 to {dims}")
        return [(i, j)]
    if dims <= 2:
        return [(0, dims - 1)]
    return [(i, j) for i in range(dims) for j in range(i + 1, dims)]


def repertoire(ax: Any, task: Task, behaviors: np.ndarray, title: str, dims: tuple[int, int] = (0, 1),
               qualities: np.ndarray | None = None, limits: tuple[float, float] | None = None) -> Any:
    """Draws behaviors [N, d] over the task's behavior box on the axes `ax`, coloured by qualities [N] (viridis,
    within `limits`, by default theirs) where given: for d = 2 over `task.layout()`; for d = 1 on a strip; for
    d > 2 their projection on the behavior dimensions `dims` (0-based; the layout, in the first two dimensions,
    only on (0, 1)), labelled as such. The legend goes below the axes, never over a skill. Returns the scatter
    (for a colour bar)."""
    d, (i, j) = task.behavior_dim, dims
    low, high = task.behavior_low, task.behavior_high
    label = f"{len(behaviors)} skill{'' if len(behaviors) == 1 else 's'}"
    colour: dict[str, Any] = {"c": "tab:blue"}
    if qualities is not None:
        lo, hi = limits if limits is not None else (float(np.min(qualities, initial=0.0)),
                                                     float(np.max(qualities, initial=1.0)))
        colour = {"c": qualities, "cmap": "viridis", "vmin": lo, "vmax": hi if hi > lo else lo + 1e-6}
    if d == 1:
        points = ax.scatter(behaviors[:, 0], np.zeros(len(behaviors)), s=30, marker="|", label=label, **colour)
        ax.set(xlim=(low[0], high[0]), ylim=(-1, 1), yticks=[], title=title, xlabel="behavior 1")
    else:
        if (i, j) == (0, 1):
            layout(ax, task)
        points = ax.scatter(behaviors[:, i], behaviors[:, j], s=4, zorder=3, label=label, **colour)
        names = ("behavior x", "behavior y") if d == 2 else (f"behavior {i + 1}", f"behavior {j + 1}")
        ax.set(xlim=(low[i], high[i]), ylim=(low[j], high[j]), title=title if d == 2 else
               f"{title}\nprojection on behaviors {i + 1}, {j + 1} of {d}", xlabel=names[0], ylabel=names[1])
        if d == 2 or np.isclose(high[j] - low[j], high[i] - low[i]):
            ax.set_aspect("equal")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=4, fontsize=7, frameon=False)
    return points


# The metrics panel's curves: (metric, label, axis).
CURVES = (("coverage", "coverage", 0), ("qd_score", "QD-score", 1), ("max_quality", "max quality", 2),
          ("mean_quality", "mean quality", 2))


def metrics_panel(axes: Any, metrics: dict[str, np.ndarray], label: str | None = None) -> None:
    """Coverage, QD-score, and max and mean quality against rollouts on three axes, from metrics [G] (one run)
    or [S, G] (seeds: their mean and one standard deviation as a band; x: the mean rollouts)."""
    x = np.atleast_2d(metrics["num_evaluations"]).mean(0)
    for name, text, k in CURVES:
        if name not in metrics:
            continue
        y = np.atleast_2d(metrics[name])
        line, = axes[k].plot(x, y.mean(0), label=f"{label}, {text}" if label and k == 2 else label or text)
        if y.shape[0] > 1:
            axes[k].fill_between(x, y.mean(0) - y.std(0), y.mean(0) + y.std(0), alpha=0.2, color=line.get_color())
        if k == 2 and label is None:
            line.set_linestyle("-" if name == "max_quality" else "--")
    for ax, ylabel in zip(axes, ("coverage", "QD-score", "quality"), strict=True):
        ax.set(xlabel="rollouts", ylabel=ylabel, title=f"{ylabel} against rollouts")
    axes[2].legend(fontsize=7)


def run_fig(task: Task, metrics: dict[str, np.ndarray], behaviors: np.ndarray, title: str,
            qualities: np.ndarray | None = None) -> Any:
    """The figure of one run (not saved): the metrics panel (`metrics_panel`), and the final repertoire over the
    layout coloured by quality with a colour bar (for d > 2 each pairwise projection), under `title`."""
    plt = pyplot()
    panels = projections(task.behavior_dim)
    columns = min(4, 3 + len(panels))
    rows = -(-(3 + len(panels)) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4.6 * columns, 4.4 * rows), squeeze=False)
    fig.suptitle(title)
    axes = list(axes.flat)
    metrics_panel(axes[:3], metrics)
    limits = None if qualities is None or not len(qualities) else (float(np.min(qualities)),
                                                                     float(np.max(qualities)))
    for ax, dims in zip(axes[3:], panels, strict=False):
        points = repertoire(ax, task, behaviors, "final repertoire", dims, qualities, limits)
        if qualities is not None:
            fig.colorbar(points, ax=ax, label="quality", shrink=0.85)
    for ax in axes[3 + len(panels):]:
        ax.axis("off")
    return fig


def run_figure(task: Task, metrics: dict[str, np.ndarray], behaviors: np.ndarray, path: str, title: str,
               description: str | None = None, qualities: np.ndarray | None = None) -> str | None:
    """Writes `run_fig` to `path` (PNG) and returns it, or None without matplotlib."""
    if pyplot() is None:
        return None
    return save(run_fig(task, metrics, behaviors, title, qualities), path, description)


def state_fig(state: Any, metrics: dict[str, Any], cfg: Any, title: str | None = None) -> Any:
    """`run_fig` of a run's final `state` and its `metrics` (what `run_mqd(key, cfg)` returns): the figure, not
    saved (a notebook shows it)."""
    from mqd_jax.core.state import get_task

    rep = jax.device_get(state.repertoire)
    n = int(rep.count)
    title = title or f"{cfg.task_name}, {cfg.algorithm_name}, {len(np.asarray(metrics['coverage']))} generations"
    return run_fig(get_task(cfg), {k: np.asarray(v) for k, v in metrics.items()}, np.asarray(rep.behaviors[:n]),
                   title, np.asarray(rep.qualities[:n]))


def of_state(state: Any, metrics: dict[str, Any], cfg: Any, path: str, title: str | None = None) -> str | None:
    """`state_fig` written to `path` (PNG) and returned, or None without matplotlib."""
    if pyplot() is None:
        return None
    return save(state_fig(state, metrics, cfg, title), path)


def figure2(task: Task, name: str, runs: dict[str, Runs], path: str, pair: tuple[int, int] | None = None) -> str | None:
    """Figure 2 for one task: coverage, QD-score and quality against rollouts (mean over seeds and one std band;
    x: the mean rollouts at each generation) per algorithm, and seed 0's final repertoire of each over the layout,
    coloured by quality on one scale with a colour bar (for d > 2 its projection on `pair`, by default the first
    two behavior dimensions)."""
    plt = pyplot()
    if plt is None:
        return None
    fig, axes = plt.subplots(1, 3 + len(runs), figsize=(4.6 * (3 + len(runs)), 4.6))
    fig.suptitle(f"{name}: {', '.join(f'{NAMES.get(a, a)} ({len(r.keys)} seeds)' for a, r in runs.items())}")
    for alg, r in runs.items():
        metrics_panel(axes[:3], r.metrics, NAMES.get(alg, alg))
    for ax in axes[:2]:
        ax.legend(fontsize=7)
    seed0 = [r.qualities[0, :r.count[0]] for r in runs.values()]
    limits = (float(min(np.min(q, initial=np.inf) for q in seed0)), float(max(np.max(q, initial=-np.inf)
                                                                             for q in seed0)))
    limits = limits if np.isfinite(limits).all() else None
    for ax, (alg, r), q in zip(axes[3:], runs.items(), seed0, strict=True):
        points = repertoire(ax, task, r.behaviors[0, :r.count[0]], f"{NAMES.get(alg, alg)}, seed 0",
                            projections(task.behavior_dim, pair)[0], q, limits)
    fig.colorbar(points, ax=axes[-1], label="quality (one scale for all)", shrink=0.85)
    return save(fig, path)


def adaptation_figure(results: dict[str, dict[str, dict[str, list[float]]]], metric: str, label: str,
                      path: str, title: str | None = None) -> str | None:
    """Figures 3 ("error") and 4 ("steps"): per task, a bar per method, mean and std over repertoires."""
    plt = pyplot()
    if plt is None:
        return None
    fig, ax = plt.subplots(figsize=(1.8 + 1.6 * len(results), 4))
    width = 0.8 / len(METHODS)
    for j, method in enumerate(METHODS):
        means = [np.mean(results[t][method][metric]) for t in results]
        stds = [np.std(results[t][method][metric]) for t in results]
        ax.bar(np.arange(len(results)) + j * width, means, width, yerr=stds, capsize=3, label=method)
    ax.set_xticks(np.arange(len(results)) + width * (len(METHODS) - 1) / 2, list(results))
    ax.set_ylabel(label)
    ax.set_title(title or f"adaptation: {label} per task and method")
    # Outside the axes, so that no bar or error bar is hidden behind it.
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    return save(fig, path)


def path_frames(task: Task, path: np.ndarray, width: int, height: int, title: str) -> np.ndarray:
    """Frames [F, height, width, 3] uint8 of a behavior moving along path [F, 2] over the task's layout."""
    plt = pyplot()
    if plt is None:
        raise ValueError("drawing a 2D skill needs matplotlib: pip install -e .[plot]")
    fig, ax = plt.subplots(figsize=(width / 100, height / 100), dpi=100)
    frames = []
    for i in range(len(path)):
        ax.clear()
        layout(ax, task)
        ax.plot(path[:i + 1, 0], path[:i + 1, 1], c="tab:blue", lw=1.5)
        ax.scatter(path[i:i + 1, 0], path[i:i + 1, 1], s=25, c="tab:blue", zorder=3)
        ax.set(xlim=(task.behavior_low[0], task.behavior_high[0]),
               ylim=(task.behavior_low[1], task.behavior_high[1]), aspect="equal", xticks=[], yticks=[])
        ax.set_title(title, fontsize=8)
        fig.canvas.draw()
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    plt.close(fig)
    return np.stack(frames)


def write_animation(frames: np.ndarray, path: str, fps: float = 12.0) -> str:
    """Writes frames [F, H, W, 3] uint8 as an animated GIF (Pillow, matplotlib's dependency) and says so."""
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    buffer = io.BytesIO()
    images[0].save(buffer, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    write_atomically(path, buffer.getvalue())
    print(f"wrote {path} ({len(frames)} frames)")
    return path
