"""Files that parse, carry a correct checksum and still say something no run makes are refused, naming the field;
a sweep killed between a batch's files finishes it from its checkpoint; hints run as printed; sizes are checked
before anything is allocated; a run folder's decisions, each without running anything (`checkpoint._check_values`,
`files.read_json`, `messages.command`, `run_folder.RunFolder`, `sweep_folder.SweepFolder`)."""

import dataclasses
import hashlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from flax import serialization

from mqd_jax import Config
from mqd_jax.experiment import checkpoint, cli, files, folders, manifest, messages, progress, results
from mqd_jax.experiment import sweep as sweep_lib
from mqd_jax.experiment.run_folder import RunFolder
from mqd_jax.experiment.sweep_folder import SweepFolder

TINY = ["--generations", "2", "--population", "8", "--capacity", "64", "--archive-capacity", "16", "--algorithm",
        "qd", "--task", "obstacle2d"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A finished tiny run in a folder whose name holds a newline."""
    folder = tmp_path_factory.mktemp("made") / "my\nrun"
    cli.main(["run", *TINY, "--out", str(folder)])
    return folder


def resealed(run, tmp_path, change):
    """The run's checkpoint with `change(body)` applied and a correct checksum: what a forger (or a bug) writes."""
    payload = serialization.msgpack_restore((run / "checkpoint.msgpack").read_bytes())
    body = serialization.msgpack_restore(payload["body"])
    change(body)
    raw = serialization.msgpack_serialize(body)
    path = tmp_path / "checkpoint.msgpack"
    path.write_bytes(serialization.msgpack_serialize({**payload, "body": raw,
                                                      "sha256": hashlib.sha256(raw).hexdigest()}))
    return str(path), Config.from_dict(body["config"]), body["key"]


def setting(*where_value):
    """A change of the body: (path of keys, value or function of the old value) pairs."""
    def change(body):
        for where, value in zip(where_value[::2], where_value[1::2], strict=True):
            *outer, last = where
            node = body
            for key in outer:
                node = node[key]
            node[last] = value(node[last]) if callable(value) else value
    return change


def _nan(x):
    return np.full_like(x, np.nan)


def _far_neighbour(x):
    x = x.copy()
    x[0, 0] = 10**6
    return x


def _negative_first(x):
    x = x.copy()
    x.flat[0] = -1
    return x


def _metric(value):
    return lambda x: np.full(x.shape, value)


IMPOSSIBLE = [
    (setting(("state", "repertoire", "count"), np.asarray(-5, np.int32)), "'repertoire.count' holds -5 skills"),
    (setting(("state", "repertoire", "count"), np.asarray(65, np.int32)), "'repertoire.count' holds 65 skills"),
    (setting(("state", "repertoire", "behaviors"), _nan), "'repertoire.behaviors' holds a value that is not finite"),
    (setting(("state", "repertoire", "neighbours", "index"), _far_neighbour),
     "'repertoire.neighbours.index' holds 1000000"),
    (setting(("state", "num_evaluations"), np.asarray(-3, np.int32),
             ("metrics", "num_evaluations"), lambda x: np.where(np.arange(len(x)) == len(x) - 1, -3, x)),
     "'num_evaluations' holds a negative count"),
    (setting(("state", "coverage", "counts"), _negative_first), "'coverage.counts' holds a negative count"),
    (setting(("state", "archive", "total"), np.asarray(-1, np.int32)), "'archive.total' holds a negative count"),
    (setting(("state", "repertoire", "qualities"), lambda x: x.astype(np.float64)),
     r"'repertoire.qualities' is float64\[64\], where this config's state has float32\[64\]"),
    *[(setting(("metrics", "coverage"), _metric(np.float32(v))), "metric 'coverage' holds a value outside")
      for v in (np.nan, np.inf, 7.5, -3.0)],
    (setting(("metrics", "added"), _metric(8.5)), "metric 'added' is float64, where a run's is int32"),
    (setting(("metrics", "coverage"), lambda x: x > 0), "metric 'coverage' is bool, where a run's is float32"),
    (setting(("metrics", "coverage"), lambda x: x.astype(np.float64)), "metric 'coverage' is float64"),
    (setting(("metrics", "coverage"), lambda x: x.astype(np.complex64)), "metric 'coverage' is complex64"),
]


@pytest.mark.parametrize(("change", "message"), IMPOSSIBLE, ids=[m for _, m in IMPOSSIBLE])
def test_a_resealed_checkpoint_that_says_something_impossible_is_refused_naming_the_field(run, tmp_path, change,
                                                                                          message):
    path, cfg, key = resealed(run, tmp_path, change)
    with pytest.raises(checkpoint.Refused, match=message):
        checkpoint.load(path, cfg, key)


def test_resume_refuses_an_impossible_count_in_one_line(run, tmp_path, capsys):
    folder = tmp_path / "run"
    path, _, _ = resealed(run, tmp_path, IMPOSSIBLE[0][0])
    os.makedirs(folder)
    for name in os.listdir(run):
        (folder / name).write_bytes((run / name).read_bytes())
    os.replace(path, folder / "checkpoint.msgpack")
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--resume", "--out", str(folder)])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and "'repertoire.count' holds -5 skills" in err


def test_a_value_json_cannot_hold_is_refused_naming_the_file_and_the_field(tmp_path):
    path = tmp_path / "metrics.json"
    with pytest.raises(ValueError, match=f"{str(path)!r} cannot be written: metrics.coverage is a complex"):
        folders.write_json(str(path), {"metrics": {"coverage": np.asarray([0.5 + 1j], np.complex64)}})
    assert not path.exists()


@pytest.mark.parametrize("depth", [500, 900])
def test_a_sealed_manifest_nested_too_deep_is_damaged_naming_it(tmp_path, capsys, depth):
    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(10_000)  # to seal it here
    try:
        data = {"kind": "run", "identity": {"config": json.loads("[" * depth + "]" * depth)}, "written": []}
        text = json.dumps({**data, files.CHECKSUM: files.json_digest(data)})
    finally:
        sys.setrecursionlimit(limit)
    (tmp_path / manifest.MANIFEST).write_text(text)
    with pytest.raises(SystemExit) as e:
        cli.main(["run", *TINY, "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1, err
    assert repr(str(tmp_path / manifest.MANIFEST)) in err and "nested more than 64 levels deep" in err


def test_a_sweep_killed_between_a_batch_s_files_finishes_it_from_its_checkpoint(tmp_path, capsys, monkeypatch):
    argv = ["sweep", "--tasks", "obstacle2d", "--algorithms", "qd", "--seeds", "2", "--generations", "6",
            "--population", "8", "--capacity", "64", "--archive-capacity", "16", "--chunk", "2", "--out",
            str(tmp_path)]
    write = results.write_json

    def dies_before_the_json(path, payload):
        if os.path.basename(path) == "obstacle2d_qd.json":
            raise KeyboardInterrupt  # killed after the batch's .npz, before its .json
        write(path, payload)

    monkeypatch.setattr(results, "write_json", dies_before_the_json)
    with pytest.raises(SystemExit):
        cli.main(argv)
    monkeypatch.setattr(results, "write_json", write)
    npz = np.load(tmp_path / "obstacle2d_qd.npz")
    assert not (tmp_path / "obstacle2d_qd.json").exists() and (tmp_path / ("obstacle2d_qd" + results.PART)).exists()
    monkeypatch.setattr(sweep_lib, "run_batch", lambda *a, **k: pytest.fail("a finished batch was run again"))
    capsys.readouterr()
    cli.main(argv)
    out = capsys.readouterr().out
    assert f"its batch is finished from its checkpoint obstacle2d_qd{results.PART}" in out
    assert not [n for n in os.listdir(tmp_path) if "damaged" in n]
    saved = results.load_runs(str(tmp_path))["obstacle2d"]["qd"]
    assert saved.metrics["coverage"].shape == (2, 6) and np.array_equal(saved.count, npz["count"])
    assert np.array_equal(saved.behaviors, npz["behaviors"])
    other = dataclasses.replace(saved.cfg, population_size=16)  # the folder's decisions, without running a batch
    before = sorted(os.listdir(tmp_path))
    with pytest.raises(ValueError, match=r"refused: .*population_size: saved 8, now 16.*Pass --overwrite"):
        SweepFolder(str(tmp_path)).claim([(other, saved.keys)], overwrite=False, rerun_stale=False)
    assert sorted(os.listdir(tmp_path)) == before


def test_the_sweep_folder_says_where_ctrl_c_stopped_it(tmp_path):
    folder = SweepFolder(str(tmp_path))
    assert folder.interrupted("before the first batch") == "interrupted before the first batch; no batch had finished"
    folder.finished = 2
    assert folder.interrupted("in obstacle2d qd, 2 seeds", 4, 6) == (
        "interrupted in obstacle2d qd, 2 seeds at generation 4 of 6: its checkpoint keeps them, and the same command "
        f"continues this batch from generation 4; the 2 finished batches in {str(tmp_path)!r} are kept")


def test_a_billion_seeds_are_refused_in_one_line_before_a_key_is_made(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sweep_lib, "seed_keys", lambda *a: pytest.fail("seed keys made before the size check"))
    with pytest.raises(SystemExit) as e:
        cli.main(["sweep", "--tasks", "obstacle2d", "--algorithms", "qd", "--seeds", "1000000000", "--out",
                  str(tmp_path / "sweep")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and "1000000000 runs" in err and "fewer --seeds" in err, err
    assert not (tmp_path / "sweep").exists()


@pytest.mark.parametrize("folder", ["-r", "my\nrun", "it's here", "tab\there"])
def test_a_hint_runs_as_printed_on_one_line(folder):
    hint = messages.command("mqd", "run", "--resume", ("--out", folder))
    assert "\n" not in hint
    words = subprocess.run(["bash", "-c", f"printf '%s\\0' {hint}"], capture_output=True, check=True).stdout
    assert words.decode().split("\0")[:-1] == ["mqd", "run", "--resume", f"--out={folder}"]
    assert cli._parser()[0].parse_args(["run", "--resume", f"--out={folder}"]).out == folder


def test_the_resume_refusal_of_a_folder_with_a_newline_is_one_line_whose_hint_names_it(run, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--resume", "--seed", "7", "--out", str(run)])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1, err
    hint = err.split("leave them out: `")[1].split("`")[0]
    words = subprocess.run(["bash", "-c", f"printf '%s\\0' {hint}"], capture_output=True, check=True).stdout
    assert words.decode().split("\0")[-2] == f"--out={run}"


def test_the_compile_time_record_never_follows_a_planted_link(tmp_path):
    target = tmp_path / "elsewhere.txt"
    target.write_text("someone else's file")
    cache = tmp_path / "cache"
    cache.mkdir()
    os.symlink(target, cache / progress.COMPILE_TIMES)
    cfg = Config(task="obstacle2d", algorithm="qd", population_size=8, capacity=64, archive_capacity=16)
    progress.remember_compile(str(cache), cfg, 12.5)
    assert target.read_text() == "someone else's file" and os.path.islink(cache / progress.COMPILE_TIMES)
    assert progress.last_compile(str(cache), cfg) is None
    os.unlink(cache / progress.COMPILE_TIMES)
    progress.remember_compile(str(cache), cfg, 12.5)  # a plain folder: written
    assert progress.last_compile(str(cache), cfg) == 12.5


def test_the_run_folder_decides_and_words_each_refusal_without_running_anything(run, tmp_path):
    folder = RunFolder(str(run))
    saved = manifest.identity(str(run))
    cfg = Config.from_dict(saved["config"])
    assert folder.progress() == (2, 2) and saved["seed"] == 0
    with pytest.raises(ValueError, match=r"holds this run, finished \(2 generations\): its results are there"):
        folder.claim(cfg, 0, resume=False, overwrite=False, saved=folder.progress())
    other = dataclasses.replace(cfg, population_size=16)
    with pytest.raises(ValueError, match=r"another run \(population_size: saved 8, now 16\).*--overwrite.*deletes "
                                         r"checkpoint.msgpack, .*; its checkpoint holds 2 of 2 generations"):
        folder.claim(other, 0, resume=False, overwrite=False, saved=folder.progress())
    with pytest.raises(ValueError, match="--resume and --overwrite together"):
        RunFolder.check_request(resume=True, overwrite=True)
    with pytest.raises(ValueError, match="holds no checkpoint; run without --resume"):
        RunFolder(str(tmp_path)).check_resumable()
    assert RunFolder(str(tmp_path)).interrupted(0) == "interrupted before a generation was saved; nothing was saved"
    assert folder.interrupted(5) == f"interrupted at generation 5; `{folder.resume_command()}` continues from there"
