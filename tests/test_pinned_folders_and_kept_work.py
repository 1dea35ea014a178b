"""A folder pinned for the whole command, only what mqd-jax can prove it wrote removed, a sweep's
stop that keeps the work, `--resume` from the saved config, and the smaller ways to lose a user's files or hours.
Each case failed on 0.16's main (f8099be). The cases that need a made sweep folder (FIFOs, bounded reads,
checkpoints that parse but are wrong) are in test_file_faults.py's [trust-4] section."""

import json
import os
import zlib

import jax
import numpy as np
import pytest

from mqd_jax import Config, run_mqd
from mqd_jax.core.state import init
from mqd_jax.experiment import checkpoint, cli, files, folders, manifest, results, tables
from mqd_jax.experiment import progress as progress_lib

TINY = ["--generations", "4", "--population", "8", "--capacity", "64", "--archive-capacity", "16", "--chunk", "2",
        "--algorithm", "random"]
SWEEP = ["sweep", "--tasks", "obstacle2d", "--algorithms", "qd", "--seeds", "2", "--population", "8", "--capacity",
         "64", "--archive-capacity", "16"]


def stop_after(monkeypatch, generation, then):
    """Runs `then()` right after the progress line of `generation` (a chunk's end, its checkpoint written)."""
    chunk = progress_lib.Lines.chunk

    def patched(self, done, m):
        chunk(self, done, m)
        if done == generation:
            then()

    monkeypatch.setattr(progress_lib.Lines, "chunk", patched)


def interrupt():
    raise KeyboardInterrupt


def png(path):
    """A user's own PNG (a valid 1x1 image, no mqd-jax provenance in it)."""
    def chunk(kind, body):
        return len(body).to_bytes(4, "big") + kind + body + zlib.crc32(kind + body).to_bytes(4, "big")

    header = (1).to_bytes(4, "big") * 2 + bytes([8, 0, 0, 0, 0])
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0\0"))
                     + chunk(b"IEND", b""))
    return path.read_bytes()


# 1. A folder swapped mid-run: the run finishes in the folder it started in, and says where that is.

@pytest.mark.parametrize("swap", ["folder", "link"])
def test_a_folder_swapped_mid_run_receives_nothing_and_the_run_says_where_it_wrote(tmp_path, capsys, monkeypatch,
                                                                                   swap):
    out, moved, elsewhere = tmp_path / "R", tmp_path / "R.orig", tmp_path / "elsewhere"

    def swap_folder():
        out.rename(moved)
        if swap == "link":
            elsewhere.mkdir()
            out.symlink_to(elsewhere)
        else:
            out.mkdir()
        (out / "metrics.json").write_text("the user's metrics")
        (out / "run.png").write_bytes(b"the user's picture")

    stop_after(monkeypatch, 2, swap_folder)
    cli.main(["run", *TINY, "--out", str(out)])
    err = capsys.readouterr().err
    assert sorted(os.listdir(out)) == ["metrics.json", "run.png"]  # not a byte of the run there
    assert (out / "metrics.json").read_text() == "the user's metrics"
    assert (out / "run.png").read_bytes() == b"the user's picture"
    saved = files.read_json(str(moved / "metrics.json"), "")
    _, whole = run_mqd(jax.random.PRNGKey(0), Config(algorithm="random", max_generations=4, population_size=8,
                                                     capacity=64, archive_capacity=16))
    np.testing.assert_array_equal(saved["metrics"]["coverage"], whole["coverage"])
    assert manifest.LOCK not in os.listdir(moved) and manifest.LOCK not in os.listdir(out)
    assert "was moved or replaced while this command ran" in err and f"now at {str(moved)!r}" in err


# 2. --overwrite in a folder without a sound manifest removes only what mqd-jax can prove it wrote.

def test_overwrite_never_removes_what_mqd_jax_cannot_prove_it_wrote(tmp_path, capsys, refused):
    out = tmp_path / "R"
    out.mkdir()
    picture = png(out / "run.png")
    (tmp_path / "mine.npz").write_bytes(b"mine")
    (out / "repertoire.npz").symlink_to(tmp_path / "mine.npz")
    (out / "checkpoint.msgpack").mkdir()
    err = refused(["run", *TINY, "--overwrite", "--out", str(out)], "checkpoint.msgpack (a folder), repertoire.npz (a "
                                                                     "symbolic link), run.png are not written by "
                                                                     "mqd-jax here")
    assert "never removes them" in err
    assert (out / "run.png").read_bytes() == picture and (out / "repertoire.npz").is_symlink()
    assert (out / "checkpoint.msgpack").is_dir() and (tmp_path / "mine.npz").read_bytes() == b"mine"
    # A sweep's tables and figures of the user's, named like results: refused too.
    sweep_out = tmp_path / "S"
    sweep_out.mkdir()
    (sweep_out / "table1.md").write_text("| my | table |\n")
    png(sweep_out / "fig2_mine.png")
    refused([*SWEEP, "--generations", "2", "--overwrite", "--out", str(sweep_out)],
            "fig2_mine.png, table1.md are not written by mqd-jax here")
    assert sorted(os.listdir(sweep_out)) == ["fig2_mine.png", "table1.md"]
    # What mqd-jax wrote carries its provenance, figures and tables included: without the manifest, it is proved so.
    cli.main(["run", *TINY, "--out", str(tmp_path / "ours")])
    os.remove(tmp_path / "ours" / manifest.MANIFEST)
    capsys.readouterr()
    cli.main(["run", *TINY, "--generations", "2", "--overwrite", "--out", str(tmp_path / "ours")])
    assert "--overwrite: removed checkpoint.msgpack, metrics.json, repertoire.npz, run.png" in capsys.readouterr().out


# 3. A sweep removes or sets aside only the files its manifest lists.

def test_a_sweep_never_removes_or_renames_a_users_file_named_like_a_batch(tmp_path, capsys):
    out = str(tmp_path)
    cli.main([*SWEEP, "--generations", "2", "--out", out])
    notes = tmp_path / "obstacle2d_qd.msgpack"
    notes.write_text("my notes on these runs")
    cli.main([*SWEEP, "--generations", "3", "--overwrite", "--out", out])  # the batch is replaced
    assert "removed obstacle2d_qd.json, obstacle2d_qd.npz" in capsys.readouterr().out
    assert notes.read_text() == "my notes on these runs"
    batch = tmp_path / "obstacle2d_qd.json"
    batch.write_bytes(batch.read_bytes()[:50])  # damaged: set aside, run again
    cli.main([*SWEEP, "--generations", "3", "--out", out])
    assert (tmp_path / "obstacle2d_qd.json.damaged").exists() and not (tmp_path / "obstacle2d_qd.msgpack.damaged"
                                                                         ).exists()
    assert notes.read_text() == "my notes on these runs"


# 7. A stop in the middle of a sweep's batch keeps its work: the batch resumes where it stopped, bit for bit.

def test_a_sweeps_batch_resumes_where_it_stopped_bit_for_bit(tmp_path, capsys, monkeypatch):
    argv = [*SWEEP, "--generations", "6", "--chunk", "2"]
    cli.main([*argv, "--out", str(tmp_path / "whole")])
    stop_after(monkeypatch, 4, interrupt)
    with pytest.raises(SystemExit) as e:
        cli.main([*argv, "--out", str(tmp_path / "stopped")])
    assert e.value.code == 130
    err = capsys.readouterr().err
    assert "interrupted in obstacle2d qd, 2 seeds at generation 4 of 6: its checkpoint keeps them, and the same " \
           "command continues this batch from generation 4" in err
    assert (tmp_path / "stopped" / f"obstacle2d_qd{results.PART}").exists()
    monkeypatch.undo()
    part, reads, read = str(tmp_path / "stopped" / f"obstacle2d_qd{results.PART}"), [], checkpoint.read
    monkeypatch.setattr(checkpoint, "read", lambda path: reads.append(path) or read(path))
    cli.main([*argv[:-1], "3", "--out", str(tmp_path / "stopped")])  # another --chunk: the batch keeps its own
    assert reads.count(part) == 1  # its checkpoint is read once (a large batch's is hundreds of MB)
    out = capsys.readouterr().out
    assert "continues in chunks of 2 generations, as it began" in out
    assert "resuming at generation 4 of 6" in out
    whole, stopped = (results.load_runs(str(tmp_path / f))["obstacle2d"]["qd"] for f in ("whole", "stopped"))
    for name in whole.metrics:
        np.testing.assert_array_equal(stopped.metrics[name], whole.metrics[name])
    np.testing.assert_array_equal(stopped.behaviors, whole.behaviors)
    assert not (tmp_path / "stopped" / f"obstacle2d_qd{results.PART}").exists()  # the batch is whole: it goes


# 8. --resume takes the saved config; a refusal says what --overwrite deletes; a damaged checkpoint is set aside.

def test_resume_needs_no_flags_and_refuses_flags_that_disagree(tmp_path, capsys, monkeypatch, refused):
    out = str(tmp_path)
    stop_after(monkeypatch, 2, interrupt)
    with pytest.raises(SystemExit):
        cli.main(["run", *TINY, "--seed", "3", "--out", out])
    monkeypatch.undo()
    refused(["run", "--resume", "--generations", "5", "--seed", "4", "--out", out],
            "flags given contradict (max_generations: saved 4, now 5, seed: saved 3, now 4); leave them out")
    err = refused(["run", "--generations", "7", "--out", out], "holds results of another run")
    assert "pass --overwrite to replace them: it deletes checkpoint.msgpack; its checkpoint holds 2 of 4 " \
           "generations" in err
    cli.main(["run", "--resume", "--out", out])
    saved = files.read_json(os.path.join(out, "metrics.json"), "")
    assert saved["seed"] == 3 and saved["config"]["max_generations"] == 4
    _, whole = run_mqd(jax.random.PRNGKey(3), Config(algorithm="random", max_generations=4, population_size=8,
                                                     capacity=64, archive_capacity=16))
    np.testing.assert_array_equal(saved["metrics"]["coverage"], whole["coverage"])
    # --overwrite sets a damaged checkpoint aside, never deletes it.
    path = tmp_path / "checkpoint.msgpack"
    damaged = path.read_bytes()[:200]
    path.write_bytes(damaged)
    capsys.readouterr()
    cli.main(["run", *TINY, "--seed", "3", "--overwrite", "--out", out])
    assert "set aside (damaged, never deleted) as checkpoint.msgpack.damaged" in capsys.readouterr().out
    assert (tmp_path / "checkpoint.msgpack.damaged").read_bytes() == damaged


# 9. The smaller ones.

def test_a_t_dist_that_lets_one_skill_hold_the_whole_box_is_refused_before_tracing(refused, tmp_path):
    refused(["run", "--t-dist", "2", "--out", str(tmp_path)], "its behavior box's diagonal is 1.414, so a single "
                                                               "skill would hold the whole box")
    cfg = Config(t_dist=1.4, max_generations=1, population_size=8, capacity=64)  # just under sqrt(2): allowed
    assert int(init(jax.random.PRNGKey(0), cfg).repertoire.count) == 0


def test_an_unwritable_jax_cache_folder_is_not_announced_as_kept(tmp_path):
    (tmp_path / "file").write_text("")
    before = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "file" / "cache"))  # under a file: never writable
    try:
        folder, said = cli.compilation_cache(True)
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
    assert folder is None and "cannot be written" in said and "kept" not in said


def test_an_over_long_out_is_refused_before_any_folder_is_made(tmp_path, refused):
    out = tmp_path.joinpath(*["a"] * 20, "b" * 300)
    refused(["run", *TINY, "--out", str(out)], "more than the 255 a name may have here")
    assert not (tmp_path / "a").exists()


def test_render_of_an_empty_repertoire_says_so(tmp_path, refused):
    folders.write_json(str(tmp_path / "metrics.json"), {"config": Config(max_generations=2).to_dict()})
    folders.write_npz(str(tmp_path / "repertoire.npz"), actions=np.zeros((0, 9), np.float32),
                      behaviors=np.zeros((0, 2), np.float32))
    refused(["render", str(tmp_path), "--goal", "0.5", "0.5"], "holds no skills (the run inserted none)")


def test_a_task_name_that_is_a_path_is_one_line(tmp_path, refused):
    refused(["run", "--task", "../../etc:passwd", "--out", str(tmp_path)], "is neither a registered task nor a plugin")


@pytest.mark.parametrize("argv", [["adapt", "somewhere", "--goals", "0"], [*SWEEP, "--seeds", "0"]])
def test_a_bad_count_is_one_line_without_the_usage(argv, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and "0 is invalid: expected an int >= 1" in err
    assert not err.startswith("usage")


def test_json_and_markdown_written_by_mqd_jax_prove_themselves(tmp_path):
    tables.write_markdown(["| a |"], str(tmp_path / "table1.md"), show=False)
    assert manifest.carries_provenance(str(tmp_path / "table1.md"))
    (tmp_path / "mine.md").write_text("| a |\n\n<!-- mqd-jax: not json -->\n")
    (tmp_path / "fifo.md").unlink(missing_ok=True)
    os.mkfifo(tmp_path / "fifo.md")
    assert not manifest.carries_provenance(str(tmp_path / "mine.md"))
    assert not manifest.carries_provenance(str(tmp_path / "fifo.md"))  # refused at once, not read
    assert json.loads((tmp_path / "table1.md").read_text().splitlines()[-1][len(manifest.MARK):-4])["provenance"]
