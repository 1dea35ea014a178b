"""The command line as a user meets it: starting, resuming, interrupting, help, plugins, bad input."""

import json
import logging
import os
import pathlib
import re
import subprocess
import sys
import warnings

import jax
import numpy as np
import pytest

import mqd_jax
from mqd_jax import Config, ask, init, run_mqd, tell
from mqd_jax.core import registry
from mqd_jax.experiment import checkpoint, cli
from mqd_jax.experiment import progress as progress_lib


def test_a_chunk_that_does_not_divide_the_run_compiles_no_second_program(tmp_path, caplog):
    cfg = Config(max_generations=6, population_size=8, capacity=64, archive_capacity=16)
    with jax.log_compiles(), caplog.at_level(logging.WARNING, logger="jax"):
        _, chunked = checkpoint.run_with_checkpoints(jax.random.PRNGKey(0), cfg, str(tmp_path / "c"), every=4)
    # 4 + 2 generations: one program of 4 generations (the previous version compiled a second one of 2).
    assert len([r for r in caplog.records if r.getMessage().startswith("Compiling jit(run_generations)")]) == 1
    _, whole = run_mqd(jax.random.PRNGKey(0), cfg)
    for name, values in whole.items():
        np.testing.assert_array_equal(chunked[name], values, err_msg=name)


def test_interrupt_says_where_and_resume_continues_the_counters(tmp_path, capsys, monkeypatch, tiny_flags, refused):
    argv = ["run", *tiny_flags, "--generations", "4", "--chunk", "2", "--algorithm", "mqd-paper",
            "--algorithm-option", "warmup_samples=8", "num_batches=2", "--out", str(tmp_path)]
    chunk = progress_lib.Lines.chunk

    def interrupt_after_first(self, done, m):
        chunk(self, done, m)
        raise KeyboardInterrupt

    monkeypatch.setattr(progress_lib.Lines, "chunk", interrupt_after_first)
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    assert e.value.code == 130
    captured = capsys.readouterr()
    assert f"interrupted at generation 2; `mqd run --resume --out={tmp_path}` continues" in captured.err
    assert "Traceback" not in captured.err
    monkeypatch.setattr(progress_lib.Lines, "chunk", chunk)
    refused(argv, f"holds a checkpoint of this run at generation 2 of 4: `mqd run --resume --out={tmp_path}` continues "
                  "it; --overwrite starts afresh, deleting those 2 generations")
    cli.main(["run", "--resume", "--out", str(tmp_path)])  # the saved config: no other flag needed
    out = capsys.readouterr().out
    assert "resuming at generation 2 of 4" in out
    assert re.search(r"^(compiled|loaded the compiled program from the cache|the program was ready .*) in [\d.]+ s$",
                     out, re.M), out
    metrics = json.loads((tmp_path / "metrics.json").read_text())["metrics"]
    last = [line for line in out.splitlines() if line.startswith("generation")][-1]
    assert last.startswith("generation    4/4") and f"discarded {sum(metrics['discarded']):6d}" in last
    _, whole = run_mqd(jax.random.PRNGKey(0), Config(algorithm="mqd-paper", max_generations=4, population_size=8,
                                                     capacity=64, archive_capacity=16,
                                                     algorithm_options=dict(warmup_samples=8, num_batches=2)))
    np.testing.assert_array_equal(metrics["coverage"], whole["coverage"])


def test_resume_without_a_checkpoint_and_chunk_zero_are_refused(tmp_path, capsys, refused, tiny_flags):
    refused(["run", *tiny_flags, "--resume", "--out", str(tmp_path)], "holds no checkpoint")
    refused(["run", *tiny_flags, "--chunk", "0", "--out", str(tmp_path)], "0 is invalid: expected an int >= 1")
    refused(["sweep", "--seeds", "0"], "expected an int >= 1")


def test_a_file_as_out_and_damaged_results_name_the_file(tmp_path, capsys, refused, tiny_flags):
    (tmp_path / "file").write_text("")
    refused(["run", *tiny_flags, "--out", str(tmp_path / "file")], "is a file, not a folder")
    (tmp_path / "obstacle2d_qd.json").write_text('{"config": {"task": "obst')
    (tmp_path / "obstacle2d_qd.npz").write_bytes(b"")
    refused(["plot", str(tmp_path)], f"{str(tmp_path / 'obstacle2d_qd.json')!r} cannot be read (JSONDecodeError")


def test_help_shows_the_defaults_that_apply_and_the_task_names(capsys):
    with pytest.raises(SystemExit):
        cli.main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--max-generations MAX_GENERATIONS, --generations MAX_GENERATIONS Config.max_generations (default: 100)" \
        in text
    assert "(default: 0;" in text and "(default: results/run)" in text and "(default: 25)" in text
    tasks = "hexapod_omni, hexapod_uni, object2d, obstacle2d, place, place3d, push_cube, push_sphere"
    assert tasks in text and "package.module:factory" in text
    with pytest.raises(SystemExit):
        cli.main(["sweep", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--tasks TASK [TASK ...] tasks to sweep" in text and "--algorithm-option NAME=VALUE" in text
    assert "mqd-paper: t_nov=0.04, t_qua=0.0, budgeted=False" in text  # every preset's options, with defaults


def test_numpy_scalars_in_a_config_are_the_python_values_they_hold():
    cfg = Config(population_size=np.int64(10), t_dist=np.float32(0.02), algorithm="mqd-paper",
                 algorithm_options={"budgeted": np.bool_(True), "pool_factor": np.int64(4)})
    same = Config(population_size=10, t_dist=float(np.float32(0.02)), algorithm="mqd-paper",
                  algorithm_options={"budgeted": True, "pool_factor": 4})
    assert cfg == same and hash(cfg) == hash(same)
    assert type(cfg.population_size) is int and type(cfg.t_dist) is float
    assert type(cfg.options["budgeted"]) is bool and type(cfg.options["pool_factor"]) is int


def test_tell_takes_nested_lists():
    cfg = Config(population_size=4, capacity=16)
    state = init(jax.random.PRNGKey(0), cfg)
    candidates = ask(state, cfg)
    b, q, v = registry.make("obstacle2d").evaluate(candidates.actions, candidates.key)
    from_lists, _ = tell(state, candidates, np.asarray(b).tolist(), np.asarray(q).tolist(), np.asarray(v).tolist(),
                         cfg)
    from_arrays, _ = tell(state, candidates, b, q, v, cfg)
    for x, y in zip(jax.tree.leaves(from_lists), jax.tree.leaves(from_arrays), strict=True):
        np.testing.assert_array_equal(x, y)


def test_a_plugin_task_runs_from_the_command_line(tmp_path, capsys, refused, tiny_flags):
    cli.main(["run", "--task", "plugin_tasks:make_reach", *tiny_flags, "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["config"]["task"] == "plugin_tasks:make_reach" and saved["metrics"]["repertoire_size"][-1] > 0
    refused(["run", "--task", "plugin_tasks:missing", "--out", str(tmp_path / "b")],
            "cannot load the factory 'missing' from module 'plugin_tasks'")
    refused(["run", "--task", "plugin_tasks:Reach", "--out", str(tmp_path / "b")],  # not a factory
            "task 'plugin_tasks:Reach': its factory failed (TypeError:")
    refused(["run", "--task", "os:getcwd", "--out", str(tmp_path / "b")],
            "task 'os:getcwd': its factory returned a str, not a mqd_jax.Task")


def test_a_task_from_an_installed_packages_entry_point(tmp_path, monkeypatch, entry_points_rescanned):
    info = tmp_path / "reach_plugin-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: reach-plugin\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[{registry.ENTRY_POINT_GROUP}]\nentry_reach = plugin_tasks:make_reach\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "entry_reach" in registry.registered_tasks()
    state, _ = run_mqd(jax.random.PRNGKey(0), Config(task="entry_reach", max_generations=2, population_size=8,
                                                     capacity=64, archive_capacity=16))
    assert int(state.repertoire.count) > 0


def test_the_compilation_cache_is_on_by_default_and_can_be_turned_off(tmp_path, monkeypatch):
    assert cli.compilation_cache(False) == (None, "no compilation cache (--no-cache)")
    monkeypatch.setenv(cli.CACHE_ENV, "off")
    assert cli.compilation_cache(True) == (None, f"no compilation cache ({cli.CACHE_ENV}=off)")
    # A fresh process without settings: the user's cache folder.
    env = {k: v for k, v in os.environ.items() if k not in (cli.CACHE_ENV, "JAX_COMPILATION_CACHE_DIR")}
    code = ("from mqd_jax.experiment import cli; import jax; "
            "print(cli.compilation_cache(True)[0], jax.config.jax_compilation_cache_dir)")
    out = subprocess.run([sys.executable, "-c", code], env={**env, "XDG_CACHE_HOME": str(tmp_path)},
                         capture_output=True, text=True, check=True).stdout.split()
    assert out == [str(tmp_path / "mqd-jax")] * 2
    # What the progress line says matches what happens: a folder that cannot be written leaves the cache off.
    (tmp_path / "a-file").write_text("")
    code = ("from mqd_jax.experiment import cli; import jax; "
            "print(cli.compilation_cache(True), jax.config.jax_compilation_cache_dir)")
    out = subprocess.run([sys.executable, "-c", code], env={**env, cli.CACHE_ENV: str(tmp_path / "a-file" / "x")},
                         capture_output=True, text=True, check=True).stdout
    assert out.startswith("(None, 'no compilation cache: ") and "cannot be written" in out and out.endswith("None\n")


def test_version_and_did_you_mean_for_tasks_algorithms_and_plugins(capsys, refused, tmp_path):
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"mqd-jax {mqd_jax.__version__}"
    refused(["run", "--task", "obstcle2d", "--out", str(tmp_path)], "(did you mean 'obstacle2d'?)")
    refused(["run", "--algorithm", "mdq", "--out", str(tmp_path)], "(did you mean 'mqd'?)")
    refused(["run", "--task", "no_such_package.tasks:make", "--out", str(tmp_path)],
            "is 'no_such_package' on the Python path? Run from the folder that holds it with PYTHONPATH=.")


def test_a_run_warning_is_one_line_without_the_librarys_source(monkeypatch):
    """The command line formats warnings as `warning: ...` while a command runs (not the file and source line
    Python prints by default), and restores Python's own afterwards."""
    from mqd_jax.core.diagnostics import RunWarning

    assert cli._format_warning(RunWarning("3 new niches were dropped"), RunWarning, "/lib/x.py", 9) == \
        "warning: 3 new niches were dropped\n"
    seen = []
    monkeypatch.setitem(cli._COMMANDS, "plot", lambda args: seen.append(warnings.formatwarning))
    cli.main(["plot", "nowhere"])
    assert seen == [cli._format_warning] and warnings.formatwarning is not cli._format_warning


def test_the_readmes_set_up_paragraph_names_the_files_a_run_writes_and_its_refusal(tmp_path, capsys, refused,
                                                                                  tiny_flags):
    readme = (pathlib.Path(__file__).resolve().parent.parent / "README.md").read_text()
    named = set(re.search(r"`results/run/\{([^}]*)\}`", readme).group(1).split(","))
    out = str(tmp_path / "run")
    cli.main(["run", *tiny_flags, "--out", out])
    assert {p.name for p in pathlib.Path(out).iterdir()} == named  # all of them, and nothing else
    assert "The same command again is refused: the run is finished, and `--overwrite` runs it again" in " ".join(
        readme.split())
    refused(["run", *tiny_flags, "--out", out], "--overwrite")
    cli.main(["run", *tiny_flags, "--out", out, "--overwrite"])
    assert {p.name for p in pathlib.Path(out).iterdir()} == named
