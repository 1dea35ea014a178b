"""Progress: a hook the runners call in order, a bar with the rate and the time left, and a run with progress
that is `run_mqd` bit for bit."""

import jax
import numpy as np
import pytest

from mqd_jax import run_mqd
from mqd_jax.experiment import progress as progress_lib


class Recorder(progress_lib.Progress):
    def __init__(self):
        self.events = []

    def resume(self, done, metrics):
        self.events.append(("resume", done))

    def compiling(self, cache="", last=None):
        self.events.append(("compiling",))

    def compiled(self):
        self.events.append(("compiled",))

    def chunk(self, done, metrics):
        self.events.append(("chunk", done, metrics["coverage"].shape))

    def close(self):
        self.events.append(("close",))


def test_a_run_with_progress_is_run_mqd_bit_for_bit_and_reports_each_chunk(tiny):
    cfg = tiny(max_generations=7)
    recorder = Recorder()
    state, metrics = progress_lib.run(jax.random.PRNGKey(0), cfg, chunk=3, progress=recorder)
    assert recorder.events == [("resume", 0), ("compiling",), ("compiled",), ("chunk", 3, (3,)), ("chunk", 6, (3,)),
                               ("chunk", 7, (1,)), ("close",)]
    want_state, want = run_mqd(jax.random.PRNGKey(0), cfg)
    for name in want:
        np.testing.assert_array_equal(metrics[name], want[name], err_msg=name)
    np.testing.assert_array_equal(state.repertoire.behaviors, want_state.repertoire.behaviors)


def test_the_bar_shows_the_generations_their_rate_and_the_time_left(tiny, capsys):
    pytest.importorskip("tqdm")
    cfg = tiny(max_generations=4)
    progress_lib.run(jax.random.PRNGKey(0), cfg, chunk=2, progress=progress_lib.Bar("", cfg.max_generations))
    err = capsys.readouterr().err
    assert "4/4" in err and "gen/s" in err and "<00:00" in err and "coverage" in err


def test_off_a_terminal_the_command_line_prints_lines_and_remembers_compile_times(tiny, tmp_path, capsys):
    cfg = tiny()
    lines = progress_lib.for_output("", 12, cfg, str(tmp_path))
    assert type(lines) is progress_lib.Lines  # pytest's output is not a terminal
    assert progress_lib.last_compile(str(tmp_path), cfg) is None
    progress_lib.remember_compile(str(tmp_path), cfg, 12.345)
    assert progress_lib.last_compile(str(tmp_path), cfg) == 12.35
    assert progress_lib.last_compile(str(tmp_path), tiny(max_generations=3)) is None  # another config
    lines.compiling("no cache")
    assert "the last compile of this config here took 12.3 s" in capsys.readouterr().out
    (tmp_path / progress_lib.COMPILE_TIMES).write_text("[not a dict")
    assert progress_lib.last_compile(str(tmp_path), cfg) is None


def test_adaptation_steps_show_a_bar_on_a_terminal_and_print_each_line_either_way(monkeypatch, capsys):
    pytest.importorskip("tqdm")
    for terminal in (False, True):
        monkeypatch.setattr("sys.stdout.isatty", lambda terminal=terminal: terminal)
        steps = progress_lib.Steps("adapt", 3, "method")
        assert (steps.bar is not None) == terminal
        for method in ("nearest", "linear", "model"):
            steps.step(f"obstacle2d {method}: mean error 0.01", f"obstacle2d {method}")
        steps.close()
        out, err = capsys.readouterr()
        assert [line for line in out.splitlines() if line] == [f"obstacle2d {m}: mean error 0.01"
                                                               for m in ("nearest", "linear", "model")]
        assert ("3/3" in err and "method/s" in err and "<00:00" in err) == terminal
