import functools
import importlib.util
import json
import os
import socket
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

from mqd_jax import Config
from mqd_jax.core import registry
from mqd_jax.experiment import cli, results, sweep, tables
from mqd_jax.experiment import progress as progress_lib
from mqd_jax.experiment.stats import mann_whitney
from mqd_jax.experiment.sweep import run_batch, seed_keys

TINY = dict(max_generations=6, population_size=16, capacity=128, archive_capacity=128)
MODEL = dict(warmup_samples=40, num_batches=20)


def test_chunks_do_not_change_a_batch_and_runs_keep_their_key():
    cfg = Config(**TINY)
    keys = seed_keys(3)
    _, whole = run_batch(cfg, keys)
    class Seen(progress_lib.Progress):
        def __init__(self):
            self.chunks = []

        def chunk(self, done, m):
            self.chunks.append((done, m["coverage"].shape))

    seen = Seen()
    _, chunked = run_batch(cfg, keys, chunk=4, progress=seen)
    assert seen.chunks == [(4, (3, 4)), (6, (3, 2))]
    for name in whole:
        np.testing.assert_array_equal(whole[name], chunked[name])
    # A run's results depend on its key only, not on its neighbours in the batch.
    _, swapped = run_batch(cfg, keys[::-1])
    np.testing.assert_array_equal(swapped["repertoire_size"], whole["repertoire_size"][::-1])


def test_threshold_grid_pairs_every_setting_with_the_same_seeds():
    cfg = Config(algorithm="mqd-paper", algorithm_options=MODEL, **TINY)
    assert sweep.param_names(cfg.params()) == ["t_dist", "emitter.surrogate.learning_rate", "emitter.inner.iso_sigma",
                                               "emitter.inner.line_sigma", "emitter.acquisition.t_nov",
                                               "emitter.acquisition.t_qua"]
    t_nov, t_qua = "emitter.acquisition.t_nov", "emitter.acquisition.t_qua"
    keys, params, pairs = sweep.grid(cfg, {t_nov: [0.0, 2.0], t_qua: [0.0, 2.0]}, seeds=2)
    assert pairs == [(0.0, 0.0), (0.0, 2.0), (2.0, 0.0), (2.0, 2.0)]
    np.testing.assert_array_equal(keys, np.tile(seed_keys(2), (4, 1)))
    np.testing.assert_array_equal(params.emitter.acquisition.t_nov, [0, 0, 0, 0, 2, 2, 2, 2])
    np.testing.assert_array_equal(params.emitter.acquisition.t_qua, [0, 0, 2, 2, 0, 0, 2, 2])
    np.testing.assert_array_equal(params.t_dist, np.full(8, cfg.t_dist, np.float32))
    np.testing.assert_array_equal(params.emitter.inner.iso_sigma, np.full(8, 0.02, np.float32))
    _, m = run_batch(cfg, keys, params)
    discarded = m["discarded"].sum(1)
    # t_nov 0 lets every candidate through (a predicted novelty, a mean distance, is > 0); t_nov 2 and t_qua 2
    # (beyond the unit box's diagonal and the quality range) turn down every candidate after warm-up.
    assert (discarded[:4] == 0).all()
    after_warmup = (m["num_evaluations"][6:, :-1] >= cfg.options["warmup_samples"]).sum(1)
    assert (discarded[6:] == after_warmup * cfg.population_size).all() and (discarded[6:] > 0).all()
    with pytest.raises(ValueError, match=r"Threshold\.params\.t_nov=-1"):
        sweep.grid(cfg, {t_nov: [-1.0]}, seeds=2)
    with pytest.raises(ValueError, match="mqd-paper has no traced parameter 't_nov'; its parameters: t_dist, "):
        sweep.grid(cfg, {"t_nov": [0.1]}, seeds=2)


def test_bad_batches_are_refused():
    cfg = Config(**TINY)
    with pytest.raises(ValueError, match=r"shape \(R, 2\)"):
        run_batch(cfg, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        run_batch(cfg, seed_keys(3), jax.tree.map(lambda x: x[None].repeat(2), cfg.params()))
    with pytest.raises(ValueError, match="seeds=0"):
        seed_keys(0)
    with pytest.raises(ValueError, match="seeds=True"):  # a bool is not a count
        seed_keys(True)


# One sharded batch of 3 runs; with arguments (coordinator address, process id) it is one of two processes.
_BATCH = textwrap.dedent("""
    import json, sys
    import jax, numpy as np
    if len(sys.argv) > 1:
        jax.distributed.initialize(coordinator_address=sys.argv[1], num_processes=2, process_id=int(sys.argv[2]))
    from mqd_jax import Config
    from mqd_jax.experiment.sweep import run_batch, seed_keys
    states, m = run_batch(Config(max_generations=3, population_size=8, capacity=64, archive_capacity=64),
                          seed_keys(3))
    json.dump({"devices": jax.device_count(), "processes": jax.process_count(),
               "shape": list(states.repertoire.count.shape), "coverage": m["coverage"].tolist()}, sys.stdout)
""")


def _cpu_env(devices):
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}".strip()
    return {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}


@functools.cache  # the same subprocess's result for the two tests that compare with it
def _batch_on(devices):
    out = subprocess.run([sys.executable, "-c", _BATCH], env=_cpu_env(devices), capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_the_run_axis_is_split_over_devices_and_padded():
    """Two CPU devices (forced): 3 runs are padded to 4, laid out 2 per device, and agree with this process's one
    device."""
    assert jax.device_count() == 1
    _, one = run_batch(Config(max_generations=3, population_size=8, capacity=64, archive_capacity=64), seed_keys(3))
    two = _batch_on(2)
    assert two["devices"] == 2 and two["shape"] == [3]
    np.testing.assert_allclose(two["coverage"], one["coverage"], atol=1e-6)


def test_two_processes_with_jax_distributed_gather_the_single_process_result():
    """Two local processes (jax.distributed, a local coordinator, one CPU device each) run one sharded batch;
    both gather every run's metrics, equal to one process with two devices (the same layout)."""
    with socket.socket() as s:
        s.bind(("localhost", 0))
        address = f"localhost:{s.getsockname()[1]}"
    procs = [subprocess.Popen([sys.executable, "-c", _BATCH, address, str(i)], env=_cpu_env(1),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [err[-2000:] for _, err in outs]
    got = [json.loads(out.strip().splitlines()[-1]) for out, _ in outs]
    want = _batch_on(2)
    for g in got:
        assert (g["devices"], g["processes"], g["shape"]) == (2, 2, [3])
        np.testing.assert_array_equal(g["coverage"], want["coverage"])


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep")
    argv = ["sweep", "--tasks", "obstacle2d", "--algorithms", "mqd", "qd", "--seeds", "3", "--generations", "6",
            "--population", "16", "--capacity", "128", "--archive-capacity", "128", "--algorithm-option",
            "warmup_samples=40", "num_batches=20", "--chunk", "3", "--out", str(out)]
    cli.main(argv)
    return out, argv


def test_mqd_sweep_writes_every_seed_and_generation_and_table_one(swept, capsys):
    out, argv = swept
    cfg = Config(algorithm="mqd", algorithm_options=MODEL, **TINY)
    saved = json.loads((out / "obstacle2d_mqd.json").read_text())
    assert saved["config"]["algorithm_options"]["warmup_samples"] == 40 and saved["config"]["max_generations"] == 6
    _, want = run_batch(cfg, seed_keys(3))
    for name in ("coverage", "repertoire_size", "num_evaluations", "discarded", "mean_quality"):
        np.testing.assert_array_equal(np.array(saved["metrics"][name], float), want[name])
    # Not trained before 40 evaluations (16 and 32 after generations 1 and 2): null, not NaN, in strict JSON.
    assert all(loss[:2] == [None, None] and loss[2] > 0 for loss in saved["metrics"]["model_loss"])
    rep = np.load(out / "obstacle2d_qd.npz")
    qd = json.loads((out / "obstacle2d_qd.json").read_text())
    np.testing.assert_array_equal(rep["count"], np.array(qd["metrics"]["repertoire_size"])[:, -1])
    table = (out / "table1.md").read_text()
    final = lambda alg: json.loads((out / f"obstacle2d_{alg}.json").read_text())["metrics"]["coverage"]  # noqa: E731
    cov = lambda alg: np.array(final(alg))[:, -1]  # noqa: E731
    p = mann_whitney(cov("mqd"), cov("qd"))[1]
    # Not the paper's settings: no paper value beside it (test_table_one_shows_the_papers_values_beside_its_settings).
    assert f"| obstacle2d | {cov('mqd').mean():.3f} +- {cov('mqd').std():.3f} |" in table
    assert f"| {p:.2g} |" in table
    # Figures need the optional matplotlib (CI installs only the dev extra); the results files do not.
    assert (out / "fig2_obstacle2d.png").exists() == (importlib.util.find_spec("matplotlib") is not None)
    # Running the same sweep again redoes nothing.
    capsys.readouterr()
    cli.main(argv)
    assert capsys.readouterr().out.count("already in") == 2


def test_mqd_adapt_adapts_the_saved_repertoires(swept):
    out, _ = swept
    cli.main(["adapt", str(out), "--goals", "20"])
    found = json.loads((out / "adaptation.json").read_text())["obstacle2d"]["methods"]
    # "nearest" is the distance from each goal to its nearest skill: brute force over the saved repertoires.
    rep = np.load(out / "obstacle2d_mqd.npz")
    task = registry.make("obstacle2d")
    from mqd_jax.adaptation import reachable_goals

    for i, count in enumerate(rep["count"]):
        goals = reachable_goals(task, 20, np.random.default_rng(i))
        d = np.linalg.norm(goals[:, None] - rep["behaviors"][i, :count][None], axis=-1).min(1)
        np.testing.assert_allclose(found["nearest"]["error"][i], d.mean(), rtol=1e-5)
    for method in ("linear", "model"):  # the best iterate: never worse than the start
        assert (np.array(found[method]["error"]) <= np.array(found["nearest"]["error"]) + 1e-6).all()
        assert (np.array(found[method]["steps"]) > 0).all()
    assert "| obstacle2d | 3 x 20 | model |" in (out / "adaptation.md").read_text()


def test_mqd_plot_remakes_the_tables_from_the_files(swept, tmp_path):
    out, _ = swept
    for name in os.listdir(out):
        if not name.endswith((".md", ".png")):
            (tmp_path / name).write_bytes((out / name).read_bytes())
    cli.main(["plot", str(tmp_path)])
    assert (tmp_path / "table1.md").read_text() == (out / "table1.md").read_text()


def test_adapt_and_plot_refuse_folders_without_results(tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli.main(["plot", str(tmp_path)])
    assert "holds no sweep results" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["adapt", str(tmp_path), "--tasks", "object2d"])
    assert "has no M-QD runs of 'object2d'" in capsys.readouterr().err


def test_layouts_come_from_the_tasks():
    obstacles = [r for r in registry.make("obstacle2d").layout() if r.label == "obstacle"]
    assert [(*r.low, *r.high) for r in obstacles] == list(registry.make("obstacle2d").obstacles)
    shelves = {r.label: (r.low, r.high) for r in registry.make("place").layout() if r.label.startswith("shelf")}
    # place.xml: shelf_low at (0.55, 0.3), half-size 0.15, top 8 cm; shelf_high at (0.75, -0.3), top 15 cm.
    np.testing.assert_allclose(shelves["shelf low (top 8 cm)"], [(0.4, 0.15), (0.7, 0.45)], atol=1e-9)
    np.testing.assert_allclose(shelves["shelf high (top 15 cm)"], [(0.6, -0.45), (0.9, -0.15)], atol=1e-9)


def test_results_round_trip_a_batch_of_states(swept):
    out, _ = swept
    cfg, keys, states = results.load_states(str(out), "obstacle2d")
    assert cfg == Config(algorithm="mqd", algorithm_options=MODEL, **TINY)
    np.testing.assert_array_equal(keys, seed_keys(3))
    rep = np.load(out / "obstacle2d_mqd.npz")
    np.testing.assert_array_equal(states.repertoire.count, rep["count"])
    m = rep["behaviors"].shape[1]
    np.testing.assert_array_equal(states.repertoire.behaviors[:, :m], rep["behaviors"])


def test_table_one_shows_the_papers_values_beside_its_settings_only():
    metrics = {name: np.full((2, 3), 0.5) for name in ("coverage", "mean_quality", "num_evaluations")}

    def runs(cfg):
        keys, count, behaviors = np.zeros((2, 2), np.uint32), np.ones(2, int), np.zeros((2, 1, 2))
        return results.Runs(cfg, keys, 1.0, "here", metrics, count, behaviors, np.zeros((2, 1)))

    by_alg = {"mqd-paper": runs(Config.paper("obstacle2d", algorithm="mqd-paper")),
              "qd": runs(Config.paper("obstacle2d", algorithm="qd", max_generations=30))}
    table = "\n".join(tables.table_one({"obstacle2d": by_alg}))
    assert "| obstacle2d | 0.500 +- 0.000 (paper 0.971 +- 0.018) | 0.500 +- 0.000 |" in table
