"""Ctrl-C stops a command at every moment, with one line, and a refused or interrupted command leaves no folder it
made behind (`mqd_jax.experiment.interrupts`, `folders.lock`)."""

import gc
import os
import signal
import subprocess
import sys
import time

import pytest

from mqd_jax.experiment import checkpoint, cli, interrupts

TINY = ["--generations", "100000", "--population", "8", "--capacity", "64", "--archive-capacity", "16", "--no-cache"]
COMMAND = "import sys; from mqd_jax.experiment.command import entry; sys.argv[0] = 'mqd'; entry()"


def test_ctrl_c_stops_run_and_sweep_with_one_line_while_starting_and_while_compiling(tmp_path):
    # (command, when: seconds after the start, or after the "preparing the program" line)
    moments = [("run", "start", 0.3), ("run", "preparing", 0.0), ("run", "preparing", 1.0),
               ("sweep", "preparing", 0.5)]
    procs = []
    for i, (command, _, _) in enumerate(moments):
        out = tmp_path / str(i) / "deep" / "results"  # none of it exists
        extra = ["--tasks", "obstacle2d", "--algorithms", "qd", "--seeds", "2"] if command == "sweep" else []
        procs.append((subprocess.Popen([sys.executable, "-c", COMMAND, command, *TINY, *extra, "--out", str(out)],
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), out))
    began = time.perf_counter()
    for (proc, _), (_, after, delay) in zip(procs, moments, strict=True):
        if after == "preparing":
            assert "preparing the program" in proc.stdout.readline()
            time.sleep(delay)
        else:
            time.sleep(max(0.0, began + delay - time.perf_counter()))
        proc.send_signal(signal.SIGINT)
    for (proc, out), moment in zip(procs, moments, strict=True):
        _, err = proc.communicate(timeout=60)  # stopped: not a run of 100,000 generations
        lines = err.strip().splitlines()
        assert proc.returncode == 130 and len(lines) == 1 and lines[0].startswith("interrupted"), (moment, err)
        assert not out.parent.parent.exists(), moment  # nothing made, nothing left
        if moment[0] == "sweep":
            assert lines[0] == "interrupted in obstacle2d qd, 2 seeds; no batch had finished"


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the lost one, as Python reports it
def test_a_press_python_loses_in_a_callback_is_raised_by_check_and_delivered_again():
    def swallowing(phase, info):  # Python prints "Exception ignored in" and drops what a gc callback raises
        signal.raise_signal(signal.SIGINT)

    def _xla_gc_callback(phase, info):  # jaxlib's: the press is kept, not raised there, and delivered again
        signal.raise_signal(signal.SIGINT)

    with interrupts.latched():
        gc.callbacks.append(swallowing)
        try:
            gc.collect()
        finally:
            gc.callbacks.remove(swallowing)
        with pytest.raises(KeyboardInterrupt):
            interrupts.check()  # what the chunk loops call after compiling and after every chunk
    interrupts.check()  # outside the block: forgotten
    with interrupts.latched(), pytest.raises(KeyboardInterrupt):
        gc.callbacks.append(_xla_gc_callback)
        try:
            gc.collect()
        finally:
            gc.callbacks.remove(_xla_gc_callback)
        time.sleep(2)  # the press comes again within 0.05 s


def test_a_refused_command_leaves_no_folder_and_an_interrupted_one_no_manifest(tmp_path, capsys, monkeypatch):
    deep = tmp_path / "results" / "deep" / "bad"
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--population", "-5", "--out", str(deep)])
    assert e.value.code == 2 and "population" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    kept = tmp_path / "mine"
    kept.mkdir()
    (kept / "notes.txt").write_text("a user's file")

    def pressed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(checkpoint, "run_with_checkpoints", pressed)
    with pytest.raises(SystemExit) as e:
        cli.main(["run", *TINY, "--out", str(kept)])
    assert e.value.code == 130
    assert capsys.readouterr().err.strip() == "interrupted before a generation was saved; nothing was saved"
    assert sorted(os.listdir(kept)) == ["notes.txt"]  # the user's folder as it was: no mqd.json, no lock
