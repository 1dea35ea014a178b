"""Figures as a QD paper shows them: the repertoire coloured by quality with a colour bar, coverage, QD-score and
quality against rollouts (with the seeds' spread), every figure titled, no legend over a skill."""

import numpy as np
import pytest

pytest.importorskip("matplotlib")
from matplotlib.collections import PathCollection, PolyCollection
from PIL import Image

from mqd_jax import Task
from mqd_jax.core.config import Config
from mqd_jax.core.state import get_task
from mqd_jax.experiment import plots, results


def _run(task, n=300, generations=20, seeds=None, rng=None):
    rng = rng or np.random.default_rng(0)
    low, high = np.asarray(task.behavior_low), np.asarray(task.behavior_high)
    behaviors = rng.uniform(low, high, (n, task.behavior_dim)).astype(np.float32)
    qualities = behaviors.sum(1) / task.behavior_dim  # a gradient across the box
    shape = (generations,) if seeds is None else (seeds, generations)
    grow = np.linspace(0.1, 1.0, generations)
    metrics = {"num_evaluations": np.broadcast_to(np.arange(1, generations + 1) * 100.0, shape).copy(),
               "coverage": np.broadcast_to(0.5 * grow, shape) + (0 if seeds is None else rng.normal(0, 0.02, shape)),
               "qd_score": np.broadcast_to(30 * grow, shape).copy(), "max_quality": np.broadcast_to(grow, shape).copy(),
               "mean_quality": np.broadcast_to(0.5 * grow, shape).copy()}
    return behaviors, qualities, metrics


def _colourbars(fig):
    return [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]


@pytest.mark.parametrize("dims, panels", [(2, 1), (3, 3)])
def test_a_run_figure_colours_the_repertoire_by_quality_and_plots_the_metrics(dims, panels, tmp_path):
    task = get_task(Config(task="obstacle2d")) if dims == 2 else Task((-1.0,) * 3, (1.0,) * 3, (0.0,) * 3,
                                                                     (1.0,) * 3)
    behaviors, qualities, metrics = _run(task)
    fig = plots.run_fig(task, metrics, behaviors, "a run", qualities)
    assert fig._suptitle.get_text() == "a run"
    assert len(_colourbars(fig)) == panels  # one per projection (3 behavior dimensions: 3 pairs)
    drawn = [ax for ax in fig.axes if ax.get_label() != "<colorbar>" and ax.axison]
    assert all(ax.get_title() for ax in drawn)
    curves = {line.get_label() for ax in drawn[:3] for line in ax.get_lines()}
    assert {"coverage", "QD-score", "max quality", "mean quality"} <= curves
    fig.canvas.draw()
    for ax in drawn[3:]:
        scatter = next(c for c in ax.collections if isinstance(c, PathCollection))
        np.testing.assert_allclose(scatter.get_array(), qualities)  # coloured by quality
        points = ax.transData.transform(scatter.get_offsets())
        box = ax.get_legend().get_window_extent()
        assert not ((points[:, 0] >= box.x0) & (points[:, 0] <= box.x1) & (points[:, 1] >= box.y0)
                    & (points[:, 1] <= box.y1)).any(), "the legend covers a skill"
    plots.pyplot().close(fig)
    path = plots.run_figure(task, metrics, behaviors, str(tmp_path / "run.png"), "a run", qualities=qualities)
    with Image.open(path) as image:
        assert image.width >= 1200 and image.height >= 400
        colours = {tuple(c) for c in np.asarray(image.convert("RGB")).reshape(-1, 3)[::7]}
    assert len(colours) > 200  # a colour scale, not one blue


def test_figure_2_shows_every_algorithm_with_the_seeds_spread_and_one_colour_scale(tmp_path):
    cfg = Config(task="obstacle2d")
    task = get_task(cfg)
    rng = np.random.default_rng(1)

    def runs(offset):
        behaviors, qualities, metrics = _run(task, seeds=3, rng=rng)
        return results.Runs(cfg, np.zeros((3, 2), np.uint32), 1.0, "here", metrics, np.full(3, len(behaviors)),
                            np.stack([behaviors] * 3), np.stack([qualities + offset] * 3))

    path = str(tmp_path / "fig2.png")
    assert plots.figure2(task, "obstacle2d", {"qd": runs(0.0), "mqd": runs(0.5)}, path) == path
    with Image.open(path) as image:
        assert image.width > image.height > 300
    fig = plots.pyplot().figure()
    axes = [fig.add_subplot(1, 3, k + 1) for k in range(3)]
    plots.metrics_panel(axes, runs(0.0).metrics, "QD")
    assert all(any(isinstance(c, PolyCollection) for c in ax.collections) for ax in axes)  # the std bands
    plots.pyplot().close(fig)


def test_the_adaptation_figures_are_titled(tmp_path, monkeypatch):
    saved = {}
    monkeypatch.setattr(plots, "save", lambda fig, path, description=None: saved.setdefault(path, fig) and path)
    found = {"obstacle2d": {m: {"error": [0.1, 0.2], "steps": [3, 4]} for m in ("nearest", "linear", "model")}}
    plots.adaptation_figure(found, "error", "behavioral error", "fig3.png")
    assert saved["fig3.png"].axes[0].get_title() == "adaptation: behavioral error per task and method"
