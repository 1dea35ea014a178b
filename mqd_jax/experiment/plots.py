"""Figures (matplotlib, the optional `plot` extra): a run, Figure 2, and Figures 3-4.

Every function writes one PNG and returns its path, or returns None (saying
so) when matplotlib is not installed: results files never depend on it.
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np

from mqd_jax.adaptation import METHODS
from mqd_jax.core.task import Task
from mqd_jax.experiment.folders import write_atomically
from mqd_jax.experiment.results import NAMES, Runs


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend, or None (with a message) when matplotlib is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed (pip install -e .[plot]): no figure written")
        return None
    return plt


def save(fig: Any, path: str, description: str | None = None) -> str:
    """Writes `fig` to `path` atomically (PNG, 100 dpi; `description` goes into the PNG's Description text) and
    says so."""
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100, metadata={"Description": description} if description else None)
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


def repertoire(ax: Any, task: Task, behaviors: np.ndarray, title: str) -> None:
    """Draws `task.layout()` and behaviors [N, 2] over the task's behavior box on the axes `ax`."""
    layout(ax, task)
    ax.scatter(behaviors[:, 0], behaviors[:, 1], s=2, c="tab:blue", zorder=3, label=f"behaviors ({len(behaviors)})")
    ax.set(xlim=(task.behavior_low[0], task.behavior_high[0]), ylim=(task.behavior_low[1], task.behavior_high[1]),
           aspect="equal", title=title, xlabel="behavior x", ylabel="behavior y")
    ax.legend(loc="upper right", fontsize=6, framealpha=0.7)


def run_figure(task: Task, metrics: dict[str, np.ndarray], behaviors: np.ndarray, path: str, title: str,
               description: str | None = None) -> str | None:
    """One run: coverage against evaluations, and the final repertoire over the layout, under `title`."""
    plt = pyplot()
    if plt is None:
        return None
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4.5))
    fig.suptitle(title)
    ax1.plot(metrics["num_evaluations"], metrics["coverage"])
    ax1.set(xlabel="evaluations", ylabel="coverage")
    repertoire(ax2, task, behaviors, "final repertoire")
    return save(fig, path, description)


def figure2(task: Task, name: str, runs: dict[str, Runs], path: str) -> str | None:
    """Figure 2 for one task: coverage against evaluations (mean over seeds and one std band; x: the mean
    evaluations at each generation) per algorithm, and seed 0's final repertoire of each over the layout."""
    plt = pyplot()
    if plt is None:
        return None
    fig, axes = plt.subplots(1, 1 + len(runs), figsize=(4.6 * (1 + len(runs)), 4.4))
    for alg, r in runs.items():
        x, cov = r.metrics["num_evaluations"].mean(0), r.metrics["coverage"]
        axes[0].plot(x, cov.mean(0), label=f"{NAMES[alg]} ({len(r.keys)} seeds)")
        axes[0].fill_between(x, cov.mean(0) - cov.std(0), cov.mean(0) + cov.std(0), alpha=0.25)
    axes[0].set(xlabel="evaluations", ylabel="coverage", title=name)
    axes[0].legend()
    for ax, (alg, r) in zip(axes[1:], runs.items(), strict=True):
        repertoire(ax, task, r.behaviors[0, :r.count[0]], f"{NAMES[alg]}, seed 0")
    return save(fig, path)


def adaptation_figure(results: dict[str, dict[str, dict[str, list[float]]]], metric: str, label: str,
                      path: str) -> str | None:
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
