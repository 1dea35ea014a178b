"""Behavior spaces of 1 to 8 dimensions: coverage against independent computations, its Monte Carlo error bar,
a run's coverage against its final repertoire, and the command line on a 3-D plugin task."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import plugin_tasks
import pytest
from compiled import compiled

from mqd_jax import Config, adapt, run_mqd
from mqd_jax.core import coverage
from mqd_jax.core import state as state_lib
from mqd_jax.experiment import cli
from mqd_jax.experiment import progress as progress_lib


def _ball_volume(d: int, r: float) -> float:
    return math.pi ** (d / 2) / math.gamma(d / 2 + 1) * r**d


def _grid(d: int, resolution: int, centres: np.ndarray, r: float, reachable: np.ndarray | None = None) -> float:
    low, high = np.zeros(d), np.ones(d)
    reach = np.ones((resolution,) * d, bool) if reachable is None else reachable
    cover = coverage.empty(low, high, reach, r)
    c = jnp.asarray(centres, jnp.float32)
    return float(compiled(lambda *a: coverage.fraction(coverage.stamp(*a)))(cover, c, jnp.ones(len(c), jnp.int32),
                                                                           jnp.float32(r)))


def _samples(points: np.ndarray, centres: np.ndarray, r: float) -> float:
    cover = coverage.empty_samples(points, np.ones(len(points), bool))
    c = jnp.asarray(centres, jnp.float32)
    return float(compiled(lambda *a: coverage.fraction(coverage.stamp(*a)))(cover, c, jnp.ones(len(c), jnp.int32),
                                                                           jnp.float32(r)))


def test_one_dimension_matches_the_exact_union_of_intervals():
    rng = np.random.default_rng(3)
    centres, r = rng.random((12, 1)), 0.03
    # Exact: sweep the intervals' ends (clipped to [0, 1]), adding the lengths where any interval is open.
    ends = sorted([(max(c - r, 0.0), 1) for c in centres[:, 0]] + [(min(c + r, 1.0), -1) for c in centres[:, 0]])
    exact, depth, last = 0.0, 0, 0.0
    for x, step in ends:
        exact += (x - last) if depth > 0 else 0.0
        depth, last = depth + step, x
    assert coverage.method(np.zeros(1), np.ones(1), 256, r, 200) == coverage.GRID
    assert coverage.axis_cells(1, 256) == 256**2  # in one dimension a grid has as many cells as in two
    assert _grid(1, 256**2, centres, r) == pytest.approx(exact, abs=1e-4)
    points = coverage.sample_points(np.zeros(1), np.ones(1), 65536)
    assert _samples(points, centres, r) == pytest.approx(exact, abs=0.01)


def test_three_dimensions_match_the_exact_volume_of_spheres_and_their_lens():
    r, gap = 0.12, 0.15  # two overlapping spheres (centres 0.15 apart) and a third apart, all inside the box
    centres = np.array([[0.3, 0.3, 0.3], [0.45, 0.3, 0.3], [0.7, 0.7, 0.7]])
    lens = math.pi * (4 * r + gap) * (2 * r - gap) ** 2 / 12
    exact = 3 * _ball_volume(3, r) - lens
    # The default resolution (256^3 cells) does not fit the grid's memory bound: Monte Carlo; 128^3 does.
    assert coverage.method(np.zeros(3), np.ones(3), 256, r, 200) == coverage.MONTE_CARLO
    assert coverage.method(np.zeros(3), np.ones(3), 128, 0.02, 200) == coverage.GRID
    assert _grid(3, 128, centres, r) == pytest.approx(exact, abs=0.01)
    points = coverage.sample_points(np.zeros(3), np.ones(3), 65536)
    estimate = _samples(points, centres, r)
    assert estimate == pytest.approx(exact, abs=0.01)
    assert abs(estimate - exact) <= 3 * float(coverage.standard_error(estimate, len(points)))


def test_three_dimensions_measure_the_reachable_part_only():
    half = coverage.cell_centres(np.zeros(3), np.ones(3), 64)[..., 2] < 0.5  # the lower half is reachable
    value = _grid(3, 64, np.array([[0.5, 0.5, 0.5]]), 0.2, half)
    assert value == pytest.approx(_ball_volume(3, 0.2) / 2 / 0.5, abs=0.01)


def test_the_monte_carlo_error_bar_holds_in_five_dimensions():
    # 32 disjoint balls at the corners of [0.25, 0.75]^5 (0.5 apart, radius 0.2): exactly 32 ball volumes.
    r = 0.2
    centres = np.stack(np.meshgrid(*[[0.25, 0.75]] * 5, indexing="ij"), -1).reshape(-1, 5)
    exact = len(centres) * _ball_volume(5, r)
    assert coverage.method(np.zeros(5), np.ones(5), 256, r, 200) == coverage.MONTE_CARLO
    points = coverage.sample_points(np.zeros(5), np.ones(5), 65536)  # the library's own points
    estimate = _samples(points, centres, r)
    assert abs(estimate - exact) <= 2 * float(coverage.standard_error(estimate, len(points)))
    # Independent sets of points: the stated standard error is the spread of the estimates.
    rng = np.random.default_rng(0)
    z = np.array([(e - exact) / float(coverage.standard_error(e, 4096))
                  for e in (_samples(rng.random((4096, 5)).astype(np.float32), centres, r) for _ in range(40))])
    assert 0.6 <= np.mean(np.abs(z) <= 1) <= 0.8 and np.mean(np.abs(z) <= 2) >= 0.9  # 68% and 95% of a normal
    assert abs(z.mean()) < 0.5


def test_a_stamp_window_over_the_bound_falls_back_to_monte_carlo():
    # 2-D at the default resolution: a grid; balls so large that a generation's stamps would pass the bound: not.
    assert coverage.method(np.zeros(2), np.ones(2), 256, 0.02, 200) == coverage.GRID
    assert coverage.method(np.zeros(2), np.ones(2), 256, 1.0, 200) == coverage.MONTE_CARLO
    with pytest.raises(ValueError, match="coverage_samples=1000 is invalid: expected an int from 1024 to 1048576"):
        Config(coverage_samples=1000)
    with pytest.raises(ValueError, match="coverage_samples=2097152 is invalid"):  # 2^21: past the memory bound
        Config(coverage_samples=2**21)


@pytest.mark.parametrize("dims", [1, 3, 5, 8])
def test_a_run_measures_the_coverage_of_its_final_repertoire(dims):
    """In every dimension, the coverage a run reports is the share of its points (grid cells or Monte Carlo
    samples) within t_dist of a skill of its final repertoire: stamping and unstamping are exact."""
    cfg = Config(task=plugin_tasks.make_waves(dims), max_generations=4, population_size=16, capacity=48,
                 archive_capacity=16, t_dist=0.2, coverage_resolution=64 if dims == 3 else 256)
    state, m = run_mqd(jax.random.PRNGKey(0), cfg)
    assert int(m["replaced"].sum()) > 0  # some balls were unstamped
    points, reachable = state_lib.coverage_points(cfg)
    if points is None:
        cells = coverage.axis_cells(dims, cfg.coverage_resolution)
        points = coverage.cell_centres(np.zeros(dims), np.ones(dims), cells).reshape(-1, dims)
        reachable = reachable.reshape(-1)
    n = int(state.repertoire.count)
    behaviors = np.asarray(state.repertoire.behaviors[:n], np.float64)
    near = np.zeros(len(points), bool)
    for b in behaviors:
        near |= ((points - b) ** 2).sum(1) <= cfg.t_dist**2
    assert float(m["coverage"][-1]) == pytest.approx((near & reachable).sum() / reachable.sum(), abs=1e-6)
    assert state_lib.coverage_method(cfg) == (coverage.GRID if dims in (1, 3) else coverage.MONTE_CARLO)


def test_mqd_predicts_and_adapts_in_five_dimensions():
    cfg = Config(task=plugin_tasks.make_waves(5), algorithm="mqd", max_generations=6, population_size=16,
                 capacity=128, archive_capacity=32, t_dist=0.2,
                 algorithm_options=dict(warmup_samples=32, hidden_size=16, batch_size=16, num_batches=20))
    state, m = run_mqd(jax.random.PRNGKey(0), cfg)
    assert np.isfinite(np.asarray(m["prediction_error"])[3:]).all()
    goals = jnp.asarray(np.random.default_rng(0).uniform(0.2, 0.8, (8, 5)), jnp.float32)
    out = adapt(state, goals, jax.random.PRNGKey(1), cfg, "model")
    start = adapt(state, goals, jax.random.PRNGKey(1), cfg, "nearest")
    assert out.errors.shape[0] == 8 and float(np.mean(out.errors)) <= float(np.mean(start.errors)) + 1e-6


def test_a_3d_plugin_task_runs_sweeps_adapts_plots_and_says_what_render_needs(tmp_path, capsys, refused):
    task = ["--task", "plugin_tasks:make_waves", "--population", "8", "--capacity", "64", "--archive-capacity", "16",
            "--t-dist", "0.2"]
    cli.main(["run", *task, "--generations", "3", "--out", str(tmp_path / "run")])
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["coverage_measured"].startswith("Monte Carlo, 65536 reachable points of 65536, standard error")
    assert "QD-score" in capsys.readouterr().out
    refused(["render", str(tmp_path / "run"), "--goal", "0.5", "0.5"],
            "--goal 0.5 0.5 has 2 numbers: the task's behaviors have 3")
    refused(["render", str(tmp_path / "run"), "--goal", "0.5", "0.5", "0.5"], "does not render its skills")
    sweep = ["sweep", "--tasks", "plugin_tasks:make_waves", "--algorithms", "mqd", "qd", "--seeds", "2",
             "--generations", "4", "--population", "8", "--capacity", "64", "--archive-capacity", "16",
             "--t-dist", "0.2", "--algorithm-option", "warmup_samples=16", "hidden_size=8", "--out",
             str(tmp_path / "sweep")]
    cli.main(sweep)
    cli.main(["adapt", str(tmp_path / "sweep"), "--goals", "4", "--steps", "2"])
    cli.main(["plot", str(tmp_path / "sweep"), "--pair", "1", "3"])
    table = (tmp_path / "sweep" / "table1.md").read_text()
    assert "| plugin_tasks:make_waves | M-QD |" in table and "Monte Carlo, 65536 reachable points" in table
    refused(["plot", str(tmp_path / "sweep"), "--pair", "1", "4"],
            "--pair 1 4 is invalid: expected two different behavior dimensions of 1 to 3")


def test_a_monte_carlo_run_resumes_from_its_checkpoint_bit_for_bit(tmp_path):
    from mqd_jax.experiment import checkpoint

    cfg = Config(task=plugin_tasks.make_waves(5), max_generations=4, population_size=8, capacity=32,
                 archive_capacity=8, t_dist=0.2)
    whole = run_mqd(jax.random.PRNGKey(0), cfg)
    path = str(tmp_path / "run.msgpack")

    class Interrupt(progress_lib.Progress):
        def chunk(self, done, metrics):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):  # after the first chunk of 2 generations, saved
        checkpoint.run_with_checkpoints(jax.random.PRNGKey(0), cfg, path, every=2, progress=Interrupt())
    resumed = checkpoint.run_with_checkpoints(jax.random.PRNGKey(0), cfg, path, every=2)
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(resumed), strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_task_declares_the_t_dist_of_its_behavior_space_and_a_given_one_wins():
    import dataclasses

    @dataclasses.dataclass(frozen=True, eq=False)
    class Coarse(plugin_tasks.Waves):
        default_t_dist = 0.2

    coarse = Coarse(*(getattr(plugin_tasks.make_waves(4), f) for f in ("action_low", "action_high", "behavior_low",
                                                                       "behavior_high")))
    assert Config.paper_2d(task=coarse).t_dist == Config.paper_robot(task=coarse).t_dist == 0.2
    assert Config.paper(coarse, t_dist=0.05).t_dist == 0.05 and Config(task=coarse).t_dist == Config.t_dist
    bad = type("Bad", (Coarse,), {"default_t_dist": -1})
    with pytest.raises(ValueError, match="default_t_dist=-1 is invalid: None or a finite float > 0"):
        Config(task=bad(coarse.action_low, coarse.action_high, coarse.behavior_low, coarse.behavior_high))
