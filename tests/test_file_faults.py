"""Every file kind the library writes, under every fault: refused with the path named, or recovered; never
silently used, never deleted ([trust-2]).

One run folder and one sweep folder (with adaptation results) are made once; each case damages one file of a
copy (truncate, flip a byte, delete, an older mqd-jax's file, a foreign file of the same name) and runs the
command that reads it.
"""

import hashlib
import io
import json
import shutil
import struct
import zipfile

import numpy as np
import pytest

from mqd_jax.experiment import cli, folders, results

RUN_FLAGS = ["--generations", "2", "--population", "8", "--capacity", "64", "--algorithm", "random"]
SWEEP = ["sweep", "--tasks", "obstacle2d", "--algorithms", "mqd", "qd", "--seeds", "2", "--generations", "2",
         "--population", "8", "--capacity", "64", "--algorithm-option", "warmup_samples=8", "num_batches=2"]


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    root = tmp_path_factory.mktemp("made")
    cli.main(["run", *RUN_FLAGS, "--out", str(root / "run")])
    cli.main([*SWEEP, "--out", str(root / "sweep")])
    cli.main(["adapt", str(root / "sweep"), "--goals", "3"])
    return root


def truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2])


def flip(path):
    """One bit: in JSON and msgpack the middle byte (JSON stays text, a digit or a letter changes); in an npz the
    middle byte of its largest member's compressed data (elsewhere a bit may change no array)."""
    data = bytearray(path.read_bytes())
    at = len(data) // 2
    if path.suffix == ".npz":
        with zipfile.ZipFile(path) as z:
            member = max(z.infolist(), key=lambda info: info.compress_size)
        name_length, extra_length = struct.unpack("<HH", data[member.header_offset + 26:member.header_offset + 30])
        at = member.header_offset + 30 + name_length + extra_length + member.compress_size // 2
    data[at] ^= 0x01
    path.write_bytes(bytes(data))


def delete(path):
    path.unlink()


def older_version(path):
    """The file as an mqd-jax before 0.9.0 wrote it: no checksum (a checkpoint: a format from the future)."""
    if path.suffix == ".json":
        saved = json.loads(path.read_text())
        saved.pop(folders.CHECKSUM)
        path.write_text(json.dumps(saved))
    elif path.suffix == ".npz":
        with np.load(path) as f:
            arrays = {k: f[k] for k in f.files if k != folders.CHECKSUM}
        np.savez_compressed(path, **arrays)
    else:
        from flax import serialization

        path.write_bytes(serialization.msgpack_serialize({"format": 99, "body": b""}))


def foreign(path):
    """A user's own file of the same name."""
    if path.suffix == ".json":
        path.write_text('{"lab_notes": "mine"}')
    elif path.suffix == ".npz":
        buffer = io.BytesIO()
        np.savez(buffer, raw=np.arange(3))
        path.write_bytes(buffer.getvalue())
    else:
        path.write_bytes(b"my own bytes")


FAULTS = [truncate, flip, delete, older_version, foreign]
# (folder, file, the command that reads it)
FILES = [
    ("sweep", "obstacle2d_qd.json", ["plot"]),
    ("sweep", "obstacle2d_qd.npz", ["plot"]),
    ("sweep", "obstacle2d_mqd.msgpack", ["plot"]),
    ("sweep", "obstacle2d_mqd.json", ["adapt", "--goals", "3"]),
    ("sweep", folders.MANIFEST, None),  # read by the sweep that continues the folder
    ("run", "metrics.json", ["render"]),
    ("run", "repertoire.npz", ["render"]),
    ("run", "checkpoint.msgpack", None),  # read by `mqd run --resume`
]


def sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.exists() else None


@pytest.mark.parametrize("fault", FAULTS, ids=lambda f: f.__name__)
@pytest.mark.parametrize(("kind", "name", "command"), FILES, ids=[f[1] for f in FILES])
def test_a_damaged_file_is_refused_naming_it_and_never_deleted(made, tmp_path, capsys, kind, name, command, fault):
    folder = tmp_path / kind
    shutil.copytree(made / kind, folder)
    path = folder / name
    fault(path)
    after_fault = sha(path)
    capsys.readouterr()
    if command is None and kind == "run":
        argv = ["run", *RUN_FLAGS, "--out", str(folder), "--resume"]
    elif command is None:
        argv = [*SWEEP, "--out", str(folder)]
    else:
        argv = [command[0], str(folder), *command[1:]]
    if command is not None and command[0] == "render":
        argv.append("--index=-1")  # refused after reading the files, before drawing: no plot extra needed
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err  # one line
    if fault is delete and name == folders.MANIFEST:
        assert "results without a valid manifest" in err and "--overwrite" in err
    elif fault is delete and name == "checkpoint.msgpack":
        assert f"--resume: {str(folder)!r} holds no checkpoint" in err
    else:
        assert repr(str(path)) in err, err
    assert sha(path) == after_fault  # nothing deleted, nothing rewritten


@pytest.mark.parametrize("fault", [f for f in FAULTS if f is not delete], ids=lambda f: f.__name__)
def test_damaged_adaptation_results_are_left_out_of_the_tables_with_a_line_that_names_them(made, tmp_path, capsys,
                                                                                        fault):
    folder = tmp_path / "sweep"
    shutil.copytree(made / "sweep", folder)
    path = folder / results.ADAPTATION
    fault(path)
    before = sha(path)
    capsys.readouterr()
    cli.main(["plot", str(folder)])
    out = capsys.readouterr().out
    assert f"left out the adaptation results: {str(path)!r}" in out
    assert not (folder / "adaptation.md").exists() and sha(path) == before
    # `mqd adapt` of every task writes them anew and keeps the damaged file aside.
    cli.main(["adapt", str(folder), "--goals", "3"])
    assert (folder / "adaptation.md").exists()
    assert sha(folder / "adaptation.json.damaged") == before


@pytest.mark.parametrize(("name", "fault"), [("obstacle2d_qd.json", flip), ("obstacle2d_qd.json", foreign),
                                           ("obstacle2d_qd.npz", truncate)], ids=["json-flip", "json-foreign",
                                                                                  "npz-truncate"])
def test_the_sweep_runs_a_damaged_batch_again_and_keeps_the_damaged_file(made, tmp_path, capsys, name, fault):
    folder = tmp_path / "sweep"
    shutil.copytree(made / "sweep", folder)
    path = folder / name
    intact = results.load_runs(str(folder))["obstacle2d"]["qd"]
    fault(path)
    damaged = path.read_bytes()
    cli.main([*SWEEP, "--out", str(folder)])
    out = capsys.readouterr().out
    assert f"{str(path)!r}" in out and "its batch is run again" in out and "obstacle2d mqd, 2 seeds: already in" in out
    assert (folder / (name + ".damaged")).read_bytes() == damaged
    again = results.load_runs(str(folder))["obstacle2d"]["qd"]
    np.testing.assert_array_equal(again.metrics["coverage"], intact.metrics["coverage"])  # the same runs
    np.testing.assert_array_equal(again.behaviors, intact.behaviors)


def test_a_one_character_edit_of_a_result_is_refused_by_the_tables(made, tmp_path, refused):
    folder = tmp_path / "sweep"
    shutil.copytree(made / "sweep", folder)
    path = folder / "obstacle2d_qd.json"
    text = path.read_text()
    at = text.index('"wall_s": ') + len('"wall_s": ')
    path.write_text(text[:at] + ("9" if text[at] != "9" else "8") + text[at + 1:])  # still valid JSON
    json.loads(path.read_text())
    refused(["plot", str(folder)], f"{str(path)!r} does not match its checksum: it was altered or damaged")


def test_a_batch_without_the_machine_names_the_file_and_what_lacks(made, tmp_path, refused):
    folder = tmp_path / "sweep"
    shutil.copytree(made / "sweep", folder)
    path = str(folder / "obstacle2d_qd.json")
    saved = folders.read_json(path, "")
    del saved["machine"]
    folders.write_json(path, saved)
    refused(["plot", str(folder)], f"{path!r} lacks 'machine' (not a complete batch of `mqd sweep`): `mqd sweep "
                                   "--tasks obstacle2d --algorithms qd")
