"""Every file kind the library writes, under every fault: refused with the path named, or recovered; never
silently used, never deleted ([trust-2]); nothing outside its folder, nothing of the user's inside it, every
failure one line ([trust-3], issue 56: real files, real symbolic and hard links, real plugin packages in a
temporary folder and, where the machine allows mounting, a real read-only or full file system).

One run folder and one sweep folder (with adaptation results) are made once; each case damages one file of a
copy (truncate, flip a byte, delete, an older mqd-jax's file, a foreign file of the same name) and runs the
command that reads it.
"""

import contextlib
import hashlib
import io
import json
import os
import re
import shutil
import signal
import stat
import struct
import subprocess
import sys
import textwrap
import zipfile

import numpy as np
import pytest

from mqd_jax import Config
from mqd_jax.core import algorithms
from mqd_jax.experiment import cli, files, flags, folders, manifest, results, tables
from mqd_jax.experiment import sweep as sweep_lib

RUN_FLAGS = ["--generations", "2", "--population", "8", "--capacity", "64", "--archive-capacity", "16", "--algorithm",
             "random"]
TINY_SWEEP = ["sweep", "--tasks", "obstacle2d", "--seeds", "2", "--generations", "2", "--population", "8", "--capacity",
              "64", "--archive-capacity", "16"]
SWEEP = [*TINY_SWEEP, "--algorithms", "mqd", "qd", "--algorithm-option", "warmup_samples=8", "num_batches=2"]


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
    while path.suffix == ".json" and _same_json(path.read_bytes(), bytes(data)):  # a float's 17th digit, say
        data[at] ^= 0x01
        at += 1
        data[at] ^= 0x01
    path.write_bytes(bytes(data))


def _same_json(a, b):
    """Whether two JSON texts hold the same values (a flipped bit that parses to the same number changes nothing)."""
    try:
        return json.loads(a) == json.loads(b)
    except ValueError:
        return False


def delete(path):
    path.unlink()


def older_version(path):
    """The file as an mqd-jax before 0.9.0 wrote it: no checksum (a checkpoint: a format from the future)."""
    if path.suffix == ".json":
        saved = json.loads(path.read_text())
        saved.pop(files.CHECKSUM)
        path.write_text(json.dumps(saved))
    elif path.suffix == ".npz":
        with np.load(path) as f:
            arrays = {k: f[k] for k in f.files if k != files.CHECKSUM}
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
    ("sweep", manifest.MANIFEST, None),  # read by the sweep that continues the folder
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
    if fault is delete and name == manifest.MANIFEST:
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
    saved = files.read_json(path, "")
    del saved["machine"]
    folders.write_json(path, saved)
    refused(["plot", str(folder)], f"{path!r} lacks 'machine' (not a complete batch of `mqd sweep`): `mqd sweep "
                                   "--tasks obstacle2d --algorithms qd")


# [trust-3]

@pytest.fixture
def copy(made, tmp_path):
    """`copy(kind)`: a fresh copy of the made "run" or "sweep" folder (inside a folder of its own)."""
    def make(kind):
        shutil.copytree(made / kind, tmp_path / "in" / kind)
        return tmp_path / "in" / kind

    return make


def saved_manifest(folder):
    return files.read_json(str(folder / manifest.MANIFEST), "")


def forge_manifest(folder, **changes):
    """Rewrites the folder's manifest with `changes`, its checksum recomputed (anyone can: it proves integrity, not
    origin)."""
    folders.write_json(str(folder / manifest.MANIFEST), {**saved_manifest(folder), **changes})


def one_line_error(capsys, argv, match):
    """Runs `mqd argv`, which must fail with exit status 2 and one line on stderr containing `match`."""
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2, err
    assert err.count("\n") == 1 and err.startswith(f"mqd {argv[0]}: error:"), err
    assert match in err, err
    return err


# 1. --overwrite removes only plain file names of the folder that the manifest lists.

@pytest.mark.parametrize("entry", ["../victim.txt", "ABSOLUTE", "sub", 5, "link.json"])
def test_a_manifest_naming_anything_but_its_own_files_is_damaged_and_nothing_outside_is_removed(
        copy, tmp_path, capsys, entry):
    folder = copy("run")
    victim = tmp_path / "in" / "victim.txt"
    victim.write_text("precious")
    (folder / "sub").mkdir()
    (folder / "link.json").symlink_to(victim)
    entry = str(victim) if entry == "ABSOLUTE" else entry
    forge_manifest(folder, written=[*saved_manifest(folder)["written"], entry])
    err = one_line_error(capsys, ["run", *RUN_FLAGS, "--seed", "1", "--out", str(folder)], f"lists {entry!r}")
    assert "--overwrite" in err
    cli.main(["run", *RUN_FLAGS, "--seed", "1", "--out", str(folder), "--overwrite"])  # repairs: a new manifest
    assert victim.read_text() == "precious" and (folder / "sub").is_dir() and (folder / "link.json").is_symlink()
    assert saved_manifest(folder)["identity"]["seed"] == 1 and entry not in saved_manifest(folder)["written"]


def test_a_sweep_over_a_forged_run_manifest_removes_nothing_outside(copy, tmp_path, capsys):
    folder = copy("run")
    victim = tmp_path / "in" / "victim.txt"
    victim.write_text("precious")
    forge_manifest(folder, written=[*saved_manifest(folder)["written"], "../victim.txt"])
    one_line_error(capsys, [*TINY_SWEEP, "--algorithms", "qd", "--out", str(folder)], "'../victim.txt'")
    cli.main([*TINY_SWEEP, "--algorithms", "qd", "--out", str(folder), "--overwrite"])
    assert saved_manifest(folder)["kind"] == "sweep" and (folder / "obstacle2d_qd.json").exists()
    assert victim.read_text() == "precious"


# 2. The lock is never followed, and is removed when the command ends.

@pytest.mark.parametrize("link", ["symbolic", "dangling", "hard"])
def test_the_lock_file_is_never_followed_through_a_link(tmp_path, link):
    folder, target = tmp_path / "out", tmp_path / "target.txt"
    folder.mkdir()
    if link != "dangling":
        target.write_text("precious")
    (os.link if link == "hard" else os.symlink)(target, folder / manifest.LOCK)
    with pytest.raises(ValueError, match=r"symbolic link|other hard links"), folders.lock(str(folder)):
        pass
    assert (target.read_text() == "precious") if link != "dangling" else not target.exists()


def test_the_lock_file_is_removed_when_the_command_ends(tmp_path, capsys):
    with folders.lock(str(tmp_path)):
        assert (tmp_path / manifest.LOCK).read_text() == f"{os.getpid()}\n"
    assert not (tmp_path / manifest.LOCK).exists()
    one_line_error(capsys, ["plot", str(tmp_path)], "holds no sweep results")
    assert os.listdir(tmp_path) == []


HOLD_LOCK = textwrap.dedent("""
    import sys, time
    from mqd_jax.experiment import files, folders, manifest
    with folders.lock(sys.argv[1]):
        print("locked", flush=True)
        time.sleep(600)
""")


# 3. `mqd render --out` writes a new GIF, or one mqd-jax wrote in a results folder, holding that folder's lock.

def test_render_never_replaces_a_file_it_did_not_write(copy, tmp_path, capsys):
    pytest.importorskip("matplotlib", reason="drawing a 2D skill needs the plot extra")
    run, sweep = copy("run"), copy("sweep")
    before = (sweep / "obstacle2d_qd.json").read_bytes()
    one_line_error(capsys, ["render", str(run), "--out", str(sweep / "obstacle2d_qd.json")], "expected a new .gif")
    mine = tmp_path / "mine.gif"
    mine.write_bytes(b"my own")
    one_line_error(capsys, ["render", str(run), "--out", str(mine)], "exists")
    (sweep / "mine.gif").write_bytes(b"my own")
    one_line_error(capsys, ["render", str(run), "--out", str(sweep / "mine.gif")], "not written by mqd-jax")
    assert (sweep / "obstacle2d_qd.json").read_bytes() == before and mine.read_bytes() == b"my own"
    assert (sweep / "mine.gif").read_bytes() == b"my own"
    cli.main(["render", str(run), "--out", str(sweep / "skill.gif"), "--width", "40", "--height", "40"])
    assert "skill.gif" in saved_manifest(sweep)["written"]
    holder = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(sweep)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        one_line_error(capsys, ["render", str(run), "--out", str(sweep / "other.gif")], "another mqd process")
    finally:
        holder.kill()
        holder.wait()
    assert not (sweep / "other.gif").exists()


# 4. `mqd plot` and `mqd adapt` remove only what the manifest says mqd-jax wrote.

def test_plot_and_adapt_keep_the_users_files_named_like_tables(copy, capsys):
    folder = copy("sweep")
    mine = ["fig2_mine.png", "fig3_extra.png", "fig4_x.png", "notes.mqdtmp", "table1.md.mine.mqdtmp"]
    for name in mine:
        (folder / name).write_bytes(b"my own")
    ours = folder / "table1.md.abcd1234.mqdtmp"  # a killed writer's temporary file of a table mqd-jax wrote
    ours.write_bytes(b"half a table")
    cli.main(["plot", str(folder)])
    assert "left by an interrupted writer: removed table1.md.abcd1234.mqdtmp" in capsys.readouterr().out
    cli.main(["adapt", str(folder), "--goals", "3"])
    assert all((folder / name).read_bytes() == b"my own" for name in mine) and not ours.exists()
    assert (folder / "table1.md").exists() and (folder / "fig2_obstacle2d.png").exists()
    # A table the manifest does not list (the user's, named as mqd-jax names its own) is never replaced.
    forge_manifest(folder, written=[n for n in saved_manifest(folder)["written"] if n != "table1.md"])
    (folder / "table1.md").write_text("my table")
    one_line_error(capsys, ["plot", str(folder)], "table1.md' is not written by mqd-jax here")
    assert (folder / "table1.md").read_text() == "my table"


# 5. Task names that map to one file name are refused; duplicated names run once.

def test_task_names_that_map_to_one_file_name_are_refused(tmp_path, capsys, monkeypatch, registered):
    package = tmp_path / "plugins" / "pp"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "sub.py").write_text("from mqd_jax.core import registry\n\n\ndef f():\n"
                                    "    return registry.make('obstacle2d')\n")
    monkeypatch.syspath_prepend(str(tmp_path / "plugins"))
    registered("pp.sub.f", lambda: __import__("pp.sub", fromlist=["f"]).f())
    out = tmp_path / "out"
    one_line_error(capsys, [*SWEEP, "--tasks", "pp.sub:f", "pp.sub.f", "--out", str(out)],
                   "both map to the file names pp.sub.f_*")
    assert not out.exists()
    # A batch already in the folder under the other name clashes like another config.
    cfg = Config(task="pp.sub:f")
    saved = [(str(out / "pp.sub.f_qd"), {"config": {**cfg.to_dict(), "task": "pp.sub.f"}, "keys": [[0, 0]],
                                         "implementation": results.implementation(cfg)})]
    clash = results.conflicts(saved, [(cfg, np.zeros((1, 2), np.uint32))])
    assert "task: saved 'pp.sub.f', now 'pp.sub:f', one file name 'pp.sub.f'" in clash[str(out / "pp.sub.f_qd")].why


def test_duplicated_tasks_and_algorithms_run_once(tmp_path, capsys, monkeypatch):
    batches = []  # each batch run, with what the manifest planned when it began
    monkeypatch.setattr(sweep_lib, "run_batch", lambda cfg, *a, **k: batches.append(
        (cfg.task, cfg.algorithm, saved_manifest(tmp_path)["planned"])) or (_ for _ in ()).throw(KeyboardInterrupt))
    with pytest.raises(SystemExit):
        cli.main([*TINY_SWEEP, "--tasks", "obstacle2d", "obstacle2d", "--algorithms", "qd", "qd", "--out",
                  str(tmp_path)])
    assert batches == [("obstacle2d", "qd", [{"task": "obstacle2d", "algorithm": "qd", "seeds": 2}])]
    assert not tmp_path.joinpath(manifest.MANIFEST).exists()  # interrupted before writing: the folder as it was


# 6. JSON with NaN/Infinity literals, or nested too deep, is damaged.

@pytest.mark.parametrize("text", ['{"a": NaN, "sha256": "x"}', '{"a": -Infinity, "sha256": "x"}',
                                  "[" * 200_000 + "]" * 200_000])
def test_json_that_is_not_json_is_damaged_naming_the_file(tmp_path, text):
    path = tmp_path / "mqd.json"
    path.write_text(text)
    with pytest.raises(files.Damaged, match=re.escape(repr(str(path))) + " cannot be read"):
        files.read_json(str(path), "repair")


def test_a_manifest_with_nan_is_repaired_by_overwrite_and_a_batch_with_nan_is_set_aside(copy, capsys):
    run = copy("run")
    text = (run / manifest.MANIFEST).read_text()
    (run / manifest.MANIFEST).write_text(text.replace('"kind": "run"', '"kind": NaN'))
    one_line_error(capsys, ["run", *RUN_FLAGS, "--out", str(run)], "the literal NaN is not JSON")
    cli.main(["run", *RUN_FLAGS, "--seed", "1", "--out", str(run), "--overwrite"])
    assert saved_manifest(run)["kind"] == "run"
    sweep = copy("sweep")
    batch = sweep / "obstacle2d_qd.json"
    batch.write_text(batch.read_text().replace('"wall_s": ', '"wall_s": Infinity, "was": '))
    found, damaged = results.scan(str(sweep))
    assert str(sweep / "obstacle2d_qd") in damaged and [s for s, _ in found] == [str(sweep / "obstacle2d_mqd")]
    one_line_error(capsys, ["plot", str(sweep)], "obstacle2d_qd.json' cannot be read")


# 7. Results are written whatever the values: infinite metrics as "Infinity", with a warning naming them.

def test_finite_qualities_whose_sum_overflows_are_written_with_a_warning(tmp_path, registered, capsys):
    import plugin_tasks

    registered("huge", lambda: plugin_tasks.make_reach(scale=2.1e-38))  # qualities down to -3e38: finite
    with pytest.warns(files.InfiniteValues, match="metrics.qd_score") as caught:
        cli.main(["run", "--task", "huge", *RUN_FLAGS, "--out", str(tmp_path)])
    assert any("metrics.mean_quality" in str(w.message) for w in caught)
    saved = files.read_json(str(tmp_path / "metrics.json"), "")
    qd_score = np.array(saved["metrics"]["qd_score"], dtype=float)
    assert np.isneginf(qd_score[-1]) and "-Infinity" in saved["metrics"]["qd_score"]
    assert (tmp_path / "repertoire.npz").exists()
    assert np.isfinite(files.read_npz(str(tmp_path / "repertoire.npz"), "")["qualities"]).all()


# 8. A batch whose every rollout failed is marked; batches a sweep planned but did not write are named.

def test_tables_mark_runs_whose_every_rollout_failed_and_name_missing_batches(made, copy, capsys):
    by = results.load_runs(str(made / "sweep"))["obstacle2d"]
    qd = by["qd"]
    failed = {**qd.metrics, "invalid": qd.metrics["evaluations"].copy()}  # every rollout of both seeds failed
    failed["invalid"][0] = 0  # ... but for the first seed's first generation
    runs = {"obstacle2d": {"mqd": by["mqd"], "qd": results.Runs(qd.cfg, qd.keys, qd.wall_s, qd.machine, failed,
                                                               qd.count, qd.behaviors, qd.qualities)}}
    text = "\n".join(tables.table_one(runs))
    assert text.count("[every rollout failed in 1 of 2 runs]") == 2  # coverage and mean quality
    assert "Missing" not in text
    assert saved_manifest(made / "sweep")["planned"] == [{"task": "obstacle2d", "algorithm": a, "seeds": 2}
                                                   for a in ("mqd", "qd")]
    folder = copy("sweep")
    manifest.plan(str(folder), [{"task": "obstacle2d", "algorithm": "random", "seeds": 2}])  # an interrupted sweep
    cli.main(["plot", str(folder)])
    assert (folder / "table1.md").read_text().startswith("Missing: obstacle2d RANDOM: planned by `mqd sweep`")


# 9. Every failure is one line with exit status 2.

@contextlib.contextmanager
def mounted(where, options):
    """A tmpfs mounted at `where` with `options` (skips the test where mounting is not allowed)."""
    where.mkdir(exist_ok=True)
    if subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True).returncode:
        pytest.skip("mounting a tmpfs is not allowed here")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def test_a_read_only_folder_is_one_line_for_every_command(copy, tmp_path, capsys):
    pytest.importorskip("matplotlib", reason="render draws a 2D skill with the plot extra")
    run, sweep = copy("run"), copy("sweep")
    with mounted(tmp_path / "ro", "size=16m") as ro:
        shutil.copytree(run, ro / "run")
        shutil.copytree(sweep, ro / "sweep")
        subprocess.run(["mount", "-o", "remount,ro", str(ro)], check=True)
        for argv in (["run", *RUN_FLAGS, "--out", str(ro / "run"), "--resume"],
                     ["run", *RUN_FLAGS, "--out", str(ro / "new")], ["plot", str(ro / "sweep")],
                     ["render", str(ro / "run")]):
            one_line_error(capsys, argv, "Read-only file system")


def test_a_full_disk_is_one_line(tmp_path, capsys):
    with mounted(tmp_path / "small", "size=64k") as small:
        one_line_error(capsys, ["run", *RUN_FLAGS, "--out", str(small / "run")], "No space left on device")


def test_out_under_a_file_or_a_dangling_link_is_one_line(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    one_line_error(capsys, ["run", *RUN_FLAGS, "--out", str(tmp_path / "file" / "sub")], "Not a directory")
    (tmp_path / "link").symlink_to(tmp_path / "nowhere")
    one_line_error(capsys, ["run", *RUN_FLAGS, "--out", str(tmp_path / "link")], "a symbolic link to nothing")
    assert not (tmp_path / "nowhere").exists()


def test_a_task_whose_evaluate_fails_during_the_run_is_one_line(tmp_path, capsys, monkeypatch, registered):
    import plugin_tasks

    def broken(actions):
        raise RuntimeError("the robot's cable came loose")

    class Broken(plugin_tasks.Reach):
        def evaluate(self, actions, key):
            b, q, v = super().evaluate(actions, key)
            import jax

            return b, q + jax.pure_callback(broken, jax.ShapeDtypeStruct(q.shape, q.dtype), actions), v

    registered("broken", lambda: Broken((-3.14, -3.14), (3.14, 3.14), (0.0, 0.0), (1.0, 1.0)))
    # One line (JAX's own traceback of the callback held back) that names the task and the cause.
    err = one_line_error(capsys, ["run", "--task", "broken", *RUN_FLAGS, "--out", str(tmp_path)], "MQD_TRACEBACK=1")
    assert "the task 'broken' failed during the run: its host callback (jax.pure_callback) raised RuntimeError: " \
           "the robot's cable came loose" in err


@pytest.mark.parametrize(("flags", "match"), [
    (["--capacity", "100000000"], "would need about"),
    (["--population", "1000000", "--capacity", "1000000"], "would need about"),
    (["--k", "64", "--capacity", "64", "--population", "8"], "Config.k=64 is invalid: expected an int < capacity"),
])
def test_sizes_that_cannot_fit_are_refused_before_compiling(tmp_path, capsys, flags, match):
    import time

    began = time.perf_counter()
    one_line_error(capsys, ["run", *flags, "--out", str(tmp_path)], match)
    assert time.perf_counter() - began < 10  # not after compiling (74 s for the second)


def test_the_sweeps_repair_hints_are_shell_quoted(tmp_path):
    out = str(tmp_path / "my results")
    hint = results.repair(out, os.path.join(out, "obstacle2d_qd"))
    assert f"--out='{out}'" in hint


# 11. What a new user meets.

def test_a_mistyped_flag_is_one_line_that_suggests_the_flag(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--gens", "10"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith("mqd run: error: unrecognized arguments: --gens 10")
    assert "did you mean --generations?" in err and err.count("\n") == 1


def test_run_takes_the_tasks_column_and_its_help_says_so(capsys):
    parser, commands = cli._parser()
    robot = flags.config_from_flags(parser.parse_args(["run", "--task", "hexapod_omni"]), defaults=flags.RUN_DEFAULTS)
    assert robot == Config.paper("hexapod_omni", max_generations=100)
    flat = flags.config_from_flags(parser.parse_args(["run"]), defaults=flags.RUN_DEFAULTS)
    assert flat == Config.paper_2d(max_generations=100)
    text = " ".join(commands["run"].format_help().split())
    assert "--max-generations 100 unless given (default: auto)" in text
    assert "Config.max_generations (default: 100)" in text and "Table II's 2D" in text


def test_options_are_checked_in_plain_english():
    with pytest.raises(ValueError, match="expected an int \\(default 8\\)"):
        Config(algorithm="mqd", algorithm_options={"pool_factor": 2.5})


def test_a_finished_run_is_not_offered_resume(copy, capsys):
    err = one_line_error(capsys, ["run", *RUN_FLAGS, "--out", str(copy("run"))],
                         "holds this run, finished (2 generations)")
    assert "--resume" not in err


def test_adapt_and_plot_of_a_run_folder_say_they_take_a_sweeps(copy, capsys):
    run = copy("run")
    for command in ("adapt", "plot"):
        one_line_error(capsys, [command, str(run)], f"is a folder of `mqd run`: `mqd {command}` takes a folder of "
                                                    "`mqd sweep`")


def test_adapt_prints_its_table_not_table_one(copy, capsys):
    cli.main(["adapt", str(copy("sweep")), "--goals", "3"])
    out = capsys.readouterr().out
    assert "Adaptation of final M-QD repertoires" in out and "Table I" not in out


def test_a_cached_start_says_it_loads_the_compiled_program(tmp_path, capsys):
    import jax

    flags = ["run", *RUN_FLAGS, "--generations", "3"]
    jax.clear_caches()  # compiled (or loaded) here, so that the persistent cache holds it whatever ran before
    cli.main([*flags, "--out", str(tmp_path / "a")])
    capsys.readouterr()
    jax.clear_caches()  # as a new process starts, without compiled programs in memory
    cli.main([*flags, "--out", str(tmp_path / "b")])
    out = capsys.readouterr().out
    assert out.count("loaded the compiled program from the cache in") == 1 and "compiling" not in out


# 12. The README tells a new user what they need.

def test_the_readme_lists_every_option_of_every_preset():
    text = open(os.path.join(os.path.dirname(__file__), "..", "README.md")).read()
    table = text[text.index("| preset | options (defaults) |"):text.index("The model's options, Table II")]
    model = {"learning_rate", "batch_size", "num_batches", "warmup_samples", "hidden_size"}  # listed below it
    for name in algorithms.names():
        row = next(line for line in table.splitlines() if line.startswith(f"| `{name.replace('-', '_')}("))
        assert [o for o in algorithms.options(name) if f"`{o}" not in row and o not in model] == [], name


def test_ci_installs_what_the_readme_installs():
    root = os.path.join(os.path.dirname(__file__), "..")
    readme, ci = (open(os.path.join(root, p)).read() for p in ("README.md", ".ci/run"))
    extras = lambda text: {e for group in re.findall(r'pip install (?:-q )?-e "\.\[([^\]]+)\]"', text)  # noqa: E731
                           for e in group.split(",")}
    assert extras(readme) >= {"plot", "dev"} and extras(ci) == extras(readme)


# [trust-4] (issue 64) 4. A FIFO named like a result is refused at once, naming it: no command hangs, no lock is left.

@contextlib.contextmanager
def within(seconds):
    """Fails (TimeoutError) a block that runs longer than `seconds`: a command that would hang on a FIFO."""
    def expire(*_):
        raise TimeoutError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.mark.parametrize(("kind", "name", "argv"), [
    ("run", "metrics.json", ["render", "{folder}"]),
    ("run", "repertoire.npz", ["render", "{folder}"]),
    ("run", "checkpoint.msgpack", ["run", "--resume", "--out", "{folder}"]),
    ("sweep", "obstacle2d_qd.json", ["plot", "{folder}"]),
    ("sweep", "obstacle2d_mqd.msgpack", ["adapt", "{folder}", "--goals", "3"]),
    ("fresh", "metrics.json", ["run", *RUN_FLAGS, "--out", "{folder}"]),
    ("fresh", manifest.MANIFEST, ["run", *RUN_FLAGS, "--out", "{folder}"]),
], ids=lambda x: x if isinstance(x, str) else None)
def test_a_fifo_named_like_a_result_is_refused_at_once_naming_it(made, tmp_path, capsys, kind, name, argv):
    folder = tmp_path / kind
    if kind == "fresh":
        folder.mkdir()
    else:
        shutil.copytree(made / kind, folder)
        (folder / name).unlink()
    os.mkfifo(folder / name)
    with within(60):
        err = one_line_error(capsys, [a.format(folder=folder) for a in argv],
                             f"{name} (a FIFO)" if kind == "fresh" and name != manifest.MANIFEST
                             else repr(str(folder / name)))
    assert "a FIFO" in err
    assert stat.S_ISFIFO(os.lstat(folder / name).st_mode) and not (folder / manifest.LOCK).exists()


# [trust-4] 5. Reads are bounded by what the config implies: nothing past it is inflated or allocated.

def _npz(members):
    """An npz (zip) file of raw members {name: bytes}, deflated."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return buffer.getvalue()


def _npy_header(shape, dtype="<f4"):
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buffer.getvalue()


@pytest.mark.parametrize("bomb", ["inflates", "declares"])
def test_an_npz_larger_than_its_config_implies_is_refused_before_it_is_read(made, tmp_path, capsys, bomb):
    import tracemalloc

    folder = tmp_path / "run"
    shutil.copytree(made / "run", folder)
    if bomb == "inflates":  # 64 MiB of zeros in about 64 KB: an honest header, more than 64 skills can hold
        data = _npy_header((2**24,)) + bytes(2**26)
    else:  # a header that declares 2^40 floats (4 TiB) over a few bytes
        data = _npy_header((2**40,)) + bytes(16)
    path = folder / "repertoire.npz"
    path.write_bytes(_npz({"actions.npy": data, "behaviors.npy": _npy_header((1, 2)) + bytes(8)}))
    assert path.stat().st_size < 2**17
    tracemalloc.start()
    try:
        err = one_line_error(capsys, ["render", str(folder)], repr(str(path)))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert "its config implies" in err and "MemoryError" not in err
    assert peak < 2**25  # never inflated (64 MiB) nor allocated (4 TiB)


# [trust-4] 6. A checkpoint that parses but is wrong (fields missing, of another type, re-sealed with a fresh
# checksum) is refused naming the file and the field; the stop says what is kept.

def _resealed(path, edit):
    """Edits the body of the checkpoint `path` and seals it again with a fresh SHA-256, as a forger would."""
    from flax import serialization

    payload = serialization.msgpack_restore(path.read_bytes())
    body = serialization.msgpack_restore(payload["body"])
    edit(body)
    payload["body"] = serialization.msgpack_serialize(body)
    payload["sha256"] = hashlib.sha256(payload["body"]).hexdigest()
    path.write_bytes(serialization.msgpack_serialize(payload))


def _generation(body, value):
    body["state"]["generation"] = np.int32(value)


@pytest.mark.parametrize(("edit", "match"), [
    (lambda b: b.pop("config"), "it lacks the field 'config'"),
    (lambda b: b.update(metrics=[1, 2]), "its field 'metrics' is a list, not a dict"),
    (lambda b: _generation(b, -6), "it is at generation -6, which is negative"),
    (lambda b: b["metrics"].update({k: np.concatenate([v, v]) for k, v in b["metrics"].items()}),
     "is [4], where its 2 generations done make [2]"),
    (lambda b: (b["metrics"].update({k: np.concatenate([v, v]) for k, v in b["metrics"].items()}),
                _generation(b, 4)), "it is at generation 4, outside 0 to 2"),
], ids=["no-config", "metrics-a-list", "generation-negative", "metrics-repeated", "past-the-end"])
def test_a_checkpoint_that_parses_but_is_wrong_is_refused_naming_the_field(made, tmp_path, capsys, edit, match):
    folder = tmp_path / "run"
    shutil.copytree(made / "run", folder)
    path = folder / "checkpoint.msgpack"
    _resealed(path, edit)
    before = sha(path)
    err = one_line_error(capsys, ["run", *RUN_FLAGS, "--resume", "--out", str(folder)], repr(str(path)))
    assert match in err and "KeyError" not in err and "nothing was saved" not in err
    assert sha(path) == before
