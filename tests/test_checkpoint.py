import dataclasses
import hashlib
import pathlib
import shutil

import jax
import numpy as np
import pytest
from flax import serialization

from mqd_jax import Config, run_mqd
from mqd_jax.core.state import get_task
from mqd_jax.experiment import checkpoint, cli, files, folders, results

CFG = Config(task="obstacle2d", algorithm="mqd", algorithm_options=dict(warmup_samples=64, num_batches=20),
             population_size=16, max_generations=12, capacity=256, archive_capacity=64)
KEY = jax.random.PRNGKey(3)


def assert_trees_equal(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.fixture(scope="module")
def uninterrupted():
    return run_mqd(KEY, CFG)


def test_mismatched_checkpoints_are_refused(tmp_path, uninterrupted):
    path = str(tmp_path / "run.ckpt")
    state, metrics = uninterrupted
    checkpoint.save(path, state, metrics, CFG, KEY)
    with pytest.raises(ValueError, match=r"another config \(algorithm_options: saved .*'pool_factor': 8.*, now "
                                         r".*'pool_factor': 4"):
        checkpoint.load(path, dataclasses.replace(CFG, algorithm_options={**CFG.options, "pool_factor": 4}), KEY)
    with pytest.raises(ValueError, match=r"another config \(task: saved 'obstacle2d', now 'object2d'\)"):
        checkpoint.load(path, dataclasses.replace(CFG, task="object2d"), KEY)
    with pytest.raises(ValueError, match="started from another key"):
        checkpoint.load(path, CFG, jax.random.PRNGKey(4))
    with pytest.raises(ValueError, match="another config"):
        checkpoint.run_with_checkpoints(KEY, dataclasses.replace(CFG, capacity=512), path, every=5)


def test_a_checkpoint_of_another_revision_of_its_task_is_refused(tmp_path, uninterrupted, monkeypatch):
    """A task whose rollouts changed (its revision raised) refuses the skills of its earlier revision; a file
    without a revision (before 0.15) holds revision 0."""
    path = str(tmp_path / "run.ckpt")
    checkpoint.save(path, *uninterrupted, CFG, KEY)
    assert checkpoint.read(path)["task_revision"] == 0
    monkeypatch.setattr(type(get_task(CFG)), "revision", 1)
    with pytest.raises(ValueError, match=r"revision 0 of the task 'obstacle2d', which is at revision 1 here"):
        checkpoint.load(path, CFG, KEY)
    checkpoint.save(path, *uninterrupted, CFG, KEY)
    checkpoint.load(path, CFG, KEY)  # the same revision loads


def test_corrupt_checkpoints_are_refused(tmp_path, uninterrupted):
    path = tmp_path / "run.ckpt"
    checkpoint.save(str(path), *uninterrupted, CFG, KEY)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        checkpoint.load(str(path), CFG, KEY)
    path.write_bytes(b"\x93\x01\x02\x03")  # valid msgpack, not a checkpoint
    with pytest.raises(ValueError, match="not an mqd-jax checkpoint"):
        checkpoint.load(str(path), CFG, KEY)
    payload = serialization.msgpack_restore(data)
    path.write_bytes(serialization.msgpack_serialize({**payload, "format": checkpoint.FORMAT + 1}))
    with pytest.raises(ValueError, match=f"not an mqd-jax checkpoint of format 1 to {checkpoint.FORMAT}"):
        checkpoint.load(str(path), CFG, KEY)
    path.write_bytes(serialization.msgpack_serialize({**payload, "sha256": "0" * 64}))
    with pytest.raises(ValueError, match="checksum does not match"):
        checkpoint.load(str(path), CFG, KEY)


# before version 0.3 the default pool was 4
PAPER = dataclasses.replace(CFG, algorithm="mqd-paper", algorithm_options=dict(warmup_samples=64, num_batches=20,
                                                                               pool_factor=4))


@pytest.fixture(scope="module")
def uninterrupted_paper():
    return run_mqd(KEY, PAPER)


def _as_format_4(body):
    """A format-6 checkpoint body of the paper's filter as format 4 wrote it: the preset named "mqd", no
    `ensemble_size` or `optimism` in the config; one network without a member axis; no `rollouts`,
    chain's `parts` in the model emitter's state."""
    flat = {**{k: v for k, v in body["config"].items() if k != "algorithm_options"},
            **body["config"]["algorithm_options"]}  # before version 0.10 the preset's settings were fields
    config = {k: v for k, v in flat.items() if k not in ("ensemble_size", "optimism")}
    config.update(algorithm="mqd")
    flat = body["state"]["emitter"]  # format 6 holds the model in the surrogate's state; formats 4-5 beside the rest
    flat = {**{k: v for k, v in flat.items() if k != "surrogate"}, **flat["surrogate"]}
    emitter = {k: v for k, v in flat.items() if k not in ("rollouts", "parts")}
    model = dict(emitter["model"])
    squeeze = lambda tree: jax.tree.map(lambda x: x[0], tree)  # noqa: E731
    adam = dict(model["opt_state"]["inner_state"]["0"])
    adam.update(mu=squeeze(adam["mu"]), nu=squeeze(adam["nu"]))
    model.update(params=squeeze(model["params"]),
                 opt_state={**model["opt_state"], "inner_state": {**model["opt_state"]["inner_state"], "0": adam}})
    return {**body, "config": config, "state": {**body["state"], "emitter": {**emitter, "model": model}}}


def _as_format_3(body):
    """A format-4 checkpoint body as formats 1-3 wrote it: M-QD's model in `state["model"]` with Adam's state
    alone, `physics_backend` in the config."""
    state = dict(body["state"])
    emitter = state.pop("emitter")
    model = emitter["model"]
    state["model"] = {"params": model["params"], "opt_state": model["opt_state"]["inner_state"]["0"],
                      "steps": model["steps"]}
    return {**body, "state": state, "config": {**body["config"], "physics_backend": "auto"}}


def _write(path, body, version):
    packed = serialization.msgpack_serialize(body)
    path.write_bytes(serialization.msgpack_serialize({"format": version, "sha256": hashlib.sha256(packed).hexdigest(),
                                                      "body": packed}))


def test_checkpoints_of_formats_1_to_4_still_load(tmp_path, uninterrupted_paper):
    """Format 4 held one network, and its "mqd" was the paper's filter ("mqd-paper" now); formats 1-3 kept M-QD's
    model outside the emitter's state; format 1 also the coverage bounds as arrays."""
    path = tmp_path / "run.ckpt"
    checkpoint.save(str(path), *uninterrupted_paper, PAPER, KEY)
    body = _as_format_4(serialization.msgpack_restore(serialization.msgpack_restore(path.read_bytes())["body"]))
    _write(path, body, 4)
    with pytest.raises(ValueError, match="algorithm: saved 'mqd-paper', now 'mqd'"):
        checkpoint.load(str(path), CFG, KEY)
    state, metrics = checkpoint.load(str(path), PAPER, KEY)
    assert_trees_equal(state, uninterrupted_paper[0])
    assert_trees_equal(metrics, uninterrupted_paper[1])
    body = _as_format_3(body)
    _write(path, body, 3)
    state, metrics = checkpoint.load(str(path), PAPER, KEY)
    assert_trees_equal(state, uninterrupted_paper[0])
    assert_trees_equal(metrics, uninterrupted_paper[1])
    coverage = {**body["state"]["coverage"], "low": np.zeros(2, np.float32), "high": np.ones(2, np.float32)}
    old = {**body, "format": 1, "state": {**body["state"], "coverage": coverage}}
    path.write_bytes(serialization.msgpack_serialize(old))
    state, metrics = checkpoint.load(str(path), PAPER, KEY)
    assert_trees_equal(state, uninterrupted_paper[0])
    path.write_bytes(serialization.msgpack_serialize({**old, "format": 2}))  # the arrays are not part of format 2
    with pytest.raises(ValueError, match="does not fit this config"):
        checkpoint.load(str(path), PAPER, KEY)


def test_the_features_kept_per_skill_are_the_tasks_and_a_format_7_checkpoint_gets_them(tmp_path, uninterrupted):
    """"mqd" (its model takes 2D Obstacle's features) keeps each skill's features in the repertoire, computed once
    from its pool: they are the task's features of the skills' actions (0 in empty slots). A format-7 file had
    none: loading computes them from the saved actions."""
    state, metrics = uninterrupted
    rep, task = state.repertoire, get_task(CFG)
    valid = np.asarray(rep.valid)
    assert rep.features.shape == (CFG.capacity, 6) and valid.sum() > 16
    np.testing.assert_allclose(rep.features[valid], task.features(rep.actions[valid]), atol=1e-6)
    assert not np.asarray(rep.features)[~valid].any()
    path = tmp_path / "run.ckpt"
    checkpoint.save(str(path), state, metrics, CFG, KEY)
    body = serialization.msgpack_restore(serialization.msgpack_restore(path.read_bytes())["body"])
    body["state"]["repertoire"] = {k: v for k, v in body["state"]["repertoire"].items() if k != "features"}
    _write(path, body, 7)
    loaded, _ = checkpoint.load(str(path), CFG, KEY)
    np.testing.assert_allclose(loaded.repertoire.features, rep.features, atol=1e-6)
    assert_trees_equal(loaded.repertoire.replace(features=rep.features), rep)


def test_a_crash_while_saving_keeps_the_previous_checkpoint(tmp_path, uninterrupted, monkeypatch):
    path = tmp_path / "run.ckpt"
    state, metrics = uninterrupted
    checkpoint.save(str(path), state, metrics, CFG, KEY)
    before = path.read_bytes()

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(folders.os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        checkpoint.save(str(path), state.replace(generation=state.generation + 1), metrics, CFG, KEY)
    assert path.read_bytes() == before
    loaded, _ = checkpoint.load(str(path), CFG, KEY)
    assert_trees_equal(loaded, state)


def test_every_must_be_a_positive_int(tmp_path):
    with pytest.raises(ValueError, match="every=0 is invalid"):
        checkpoint.run_with_checkpoints(KEY, CFG, str(tmp_path / "x"), every=0)


DATA = pathlib.Path(__file__).resolve().parent / "data"  # folders mqd-jax 0.9.0 (format 5) and 0.10.0 (6) wrote


@pytest.mark.parametrize("version", ["v0.9.0", "v0.10.0"])
def test_folders_of_earlier_versions_resume_tabulate_and_adapt(tmp_path, capsys, version):
    """0.9.0's configs' settings become options, its checkpoints (one run, and a sweep's batch) load with the
    model moved into the surrogate's state; 0.10.0's "mqd" had neither features nor a gate, its checkpoints
    no gate; their files' checksums hold."""
    shutil.copytree(DATA / version, tmp_path / "old")
    run, sweep = tmp_path / "old" / "run", tmp_path / "old" / "sweep"
    saved = files.read_json(str(run / "metrics.json"), "")
    flags = ["--generations", "3", "--population", "8", "--capacity", "32", "--archive-capacity", "16",
             "--coverage-resolution", "16", "-O", "warmup_samples=8", "num_batches=2", "hidden_size=4",
             "features=False", "gate=False"]  # what their "mqd" was (0.11's takes both)
    cli.main(["run", "--algorithm", "mqd", *flags, "--out", str(run), "--resume"])
    assert "resuming at generation 3 of 3" in capsys.readouterr().out  # the whole run, nothing to compute
    now = files.read_json(str(run / "metrics.json"), "")["metrics"]
    assert {name: now[name] for name in saved["metrics"]} == saved["metrics"]
    assert now["qd_score"] == now["max_quality"] == [None] * 3  # 0.12's metrics: not measured before
    cfg, _, states = results.load_states(str(sweep), "obstacle2d")
    assert cfg.options["hidden_size"] == 4 and states.emitter.surrogate.model.steps.shape == (2,)
    assert (np.asarray(states.emitter.surrogate.model.steps) > 0).all()
    cli.main(["plot", str(sweep)])
    assert "| obstacle2d |" in (sweep / "table1.md").read_text()
