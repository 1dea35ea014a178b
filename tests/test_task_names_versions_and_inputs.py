"""One implementation per task name, one version in one place, --overwrite and --resume that lose
nothing, task definitions checked before anything is allocated, and the command line's small promises."""

import dataclasses
import hashlib
import importlib.metadata
import importlib.util
import json
import os
import pathlib
import re
import time

import jax
import numpy as np
import pytest

import mqd_jax
from mqd_jax import Config, Task
from mqd_jax.core import registry
from mqd_jax.core.task import BEHAVIOR_DIMS
from mqd_jax.experiment import checkpoint, cli, files, folders, manifest, plots, provenance, results, tables

ROOT = pathlib.Path(__file__).resolve().parent.parent
TINY = ["--generations", "2", "--population", "8", "--capacity", "64", "--archive-capacity", "16"]


def sweep_argv(out, *flags, algorithms=("qd",)):
    return ["sweep", "--tasks", "obstacle2d", "--algorithms", *algorithms, "--seeds", "2", *TINY, "--out", str(out),
            *flags]


def digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


# 1. A task name stands for one implementation.

def installed(tmp_path, monkeypatch, entries):
    """A distribution 'obstacle-plugin 1.0' installed on sys.path with these `mqd_jax.tasks` entry points."""
    info = tmp_path / "obstacle_plugin-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: obstacle-plugin\nVersion: 1.0\n")
    lines = "".join(f"{name} = {value}\n" for name, value in entries.items())
    (info / "entry_points.txt").write_text(f"[{registry.ENTRY_POINT_GROUP}]\n{lines}")
    monkeypatch.syspath_prepend(str(tmp_path))


@pytest.fixture
def replaced():
    """Undoes a `register(..., replace=True)` of a built-in name after the test."""
    yield
    registry._FACTORIES.pop("obstacle2d", None)
    registry._SOURCES.pop("obstacle2d", None)
    for clear in [registry._make.cache_clear, *registry._ON_REPLACE]:
        clear()


def test_a_plugin_named_like_a_built_in_is_an_error_naming_both(tmp_path, monkeypatch, entry_points_rescanned,
                                                               replaced, refused):
    installed(tmp_path, monkeypatch, {"obstacle2d": "plugin_tasks:make_reach", "no_factory": "plugin_tasks:gone"})
    built_in = f"built-in (mqd-jax {mqd_jax.__version__}, envs.obstacle2d:make)"
    both = re.escape(f"by {built_in} and entry point plugin_tasks:make_reach of obstacle-plugin 1.0")
    with pytest.raises(ValueError, match=f"task 'obstacle2d' is registered twice: {both}; choose one"):
        registry.make("obstacle2d")
    refused(["run", *TINY, "--out", str(tmp_path / "r")], "task 'obstacle2d' is registered twice")
    # An entry point whose factory is missing: one clear error.
    with pytest.raises(ValueError, match=r"task 'no_factory': cannot load its factory plugin_tasks:gone \(entry "
                                         r"point .* of obstacle-plugin 1.0\): AttributeError"):
        registry.make("no_factory")
    # Registering a taken name again is an error too; replacing it is said on purpose.
    import plugin_tasks

    with pytest.raises(ValueError, match=f"already registered {both}.* pass replace=True"):
        registry.register("obstacle2d", plugin_tasks.make_reach)
    registry.register("obstacle2d", plugin_tasks.make_reach, replace=True)
    assert registry.source("obstacle2d") == "registry.register (plugin_tasks:make_reach)"
    assert type(registry.make("obstacle2d")).__name__ == "Reach"


def test_results_record_the_implementation_and_tables_refuse_to_mix_them(tmp_path, capsys, replaced, refused):
    cli.main(sweep_argv(tmp_path))
    saved = files.read_json(str(tmp_path / "obstacle2d_qd.json"), "")
    assert saved["implementation"] == {"mqd_jax": mqd_jax.__version__, "task": registry.source("obstacle2d")}
    import plugin_tasks

    cfg = Config(task="obstacle2d", algorithm="random", max_generations=2, population_size=8, capacity=64,
                 archive_capacity=16)
    mqd_jax.run_mqd(jax.random.PRNGKey(0), cfg)  # compiled for the built-in ...
    registry.register("obstacle2d", plugin_tasks.make_reach, replace=True)
    state, _ = mqd_jax.run_mqd(jax.random.PRNGKey(0), cfg)  # ... and now runs the replacement, not that program
    assert state.repertoire.actions.shape[1] == 2
    # A batch of the plugin beside the built-in's: refused before it runs, and never tabulated together.
    err = refused(sweep_argv(tmp_path, algorithms=("random",)), "obstacle2d_qd is stale (task: saved 'built-in")
    assert "now 'registry.register (plugin_tasks:make_reach)'" in err and "--rerun-stale" in err
    keys = np.asarray(jax.random.split(jax.random.PRNGKey(0), 2))
    states, metrics = mqd_jax.experiment.sweep.run_batch(cfg, keys)
    results.save_runs(str(tmp_path / "by_hand"), cfg, keys, states, metrics, 1.0)
    for name in ("obstacle2d_qd.json", "obstacle2d_qd.npz"):  # a folder mixed by hand
        (tmp_path / "by_hand" / name).write_bytes((tmp_path / name).read_bytes())
    with pytest.raises(ValueError, match=r"mixes runs that cannot be compared.*is stale.*task: saved"):
        results.load_runs(str(tmp_path / "by_hand"))


# 2. One version, from one place; a sweep reuses only what this version wrote.

def test_the_version_has_one_place():
    tomllib = pytest.importorskip("tomllib")
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "version" not in project["project"] and project["project"]["dynamic"] == ["version"]
    assert project["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "mqd_jax.version.__version__"}
    assert importlib.metadata.version("mqd-jax") == mqd_jax.__version__  # the installed package's
    assert provenance.provenance()["versions"]["mqd-jax"] == mqd_jax.__version__  # what results record
    assert f"## {mqd_jax.__version__}" in (ROOT / "CHANGELOG.md").read_text()


def test_a_batch_of_another_version_is_not_reused(tmp_path, capsys, refused):
    cli.main(sweep_argv(tmp_path))
    path = str(tmp_path / "obstacle2d_qd.json")
    saved = files.read_json(path, "")
    saved["implementation"]["mqd_jax"] = "0.8.0"
    folders.write_json(path, saved)  # sound: as version 0.8.0 would have written it
    before = digest(tmp_path)
    refused(sweep_argv(tmp_path), f"obstacle2d_qd is stale (mqd_jax: saved '0.8.0', now '{mqd_jax.__version__}')")
    assert digest(tmp_path) == before
    cli.main(sweep_argv(tmp_path, "--rerun-stale"))
    assert "stale (another implementation): removed obstacle2d_qd.json" in capsys.readouterr().out
    assert files.read_json(path, "")["implementation"]["mqd_jax"] == mqd_jax.__version__


# 4. --overwrite removes only what mqd-jax wrote, tables and figures included, and lists it.

def test_overwrite_removes_only_the_files_mqd_jax_wrote_and_lists_them(tmp_path, capsys):
    cli.main(sweep_argv(tmp_path))
    (tmp_path / "lab_notes.json").write_text('{"mine": 1}')
    np.savez(tmp_path / "raw_data.npz", x=np.arange(3))
    (tmp_path / "fig2_mine.png").write_bytes(b"my figure")  # named like a figure, but not written by mqd-jax
    mine = {n: digest(tmp_path)[n] for n in ("lab_notes.json", "raw_data.npz", "fig2_mine.png")}
    ours = set(manifest.written(str(tmp_path)))
    figures = {"fig2_obstacle2d.png"} if importlib.util.find_spec("matplotlib") else set()  # the plot extra's
    assert {"obstacle2d_qd.json", "obstacle2d_qd.npz", "table1.md", *figures} <= ours
    capsys.readouterr()
    cli.main(["run", *TINY, "--algorithm", "random", "--out", str(tmp_path), "--overwrite"])
    out = capsys.readouterr().out
    removed = set(out.split("--overwrite: removed ")[1].split("\n")[0].split(", "))
    assert removed == ours  # the sweep's results and the tables and figures made of them
    assert {n: digest(tmp_path)[n] for n in mine} == mine
    assert not (tmp_path / "table1.md").exists() and not (tmp_path / "fig2_obstacle2d.png").exists()


def test_overwriting_batches_of_a_sweep_removes_the_tables_made_of_them_at_once(tmp_path, capsys, monkeypatch):
    cli.main(sweep_argv(tmp_path))
    assert (tmp_path / "table1.md").exists()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(mqd_jax.experiment.sweep, "run_batch", interrupted)
    with pytest.raises(SystemExit):
        cli.main(sweep_argv(tmp_path, "--t-dist", "0.03", "--overwrite"))
    assert not (tmp_path / "obstacle2d_qd.json").exists()
    assert not (tmp_path / "table1.md").exists() and not (tmp_path / "fig2_obstacle2d.png").exists()


# 5. --resume and --overwrite cannot destroy a run.

def test_starting_afresh_over_a_checkpoint_is_refused_with_the_command_that_resumes(tmp_path, capsys, refused):
    argv = ["run", *TINY, "--out", str(tmp_path)]
    cli.main(argv)
    before = digest(tmp_path)
    err = refused(argv, "holds this run, finished (2 generations): its results are there; --overwrite runs it "
                        "again")
    refused([*argv, "--resume", "--overwrite"], "--resume and --overwrite together")
    assert digest(tmp_path) == before and err.count("\n") == 1
    # Without its manifest (an older folder): still never deleted by --resume --overwrite.
    (tmp_path / manifest.MANIFEST).unlink()
    refused([*argv, "--resume", "--overwrite"], "--resume and --overwrite together")
    assert (tmp_path / "checkpoint.msgpack").exists()
    cli.main([*argv, "--overwrite"])  # said on purpose: starts afresh
    assert "--overwrite: removed" in capsys.readouterr().out


def test_a_damaged_checkpoint_says_how_to_start_afresh(tmp_path, refused):
    argv = ["run", *TINY, "--out", str(tmp_path)]
    cli.main(argv)
    path = tmp_path / "checkpoint.msgpack"
    path.write_bytes(path.read_bytes()[:100])
    refused([*argv, "--resume"], "the run cannot continue from it. The run's own command with --overwrite (in place "
                                 "of --resume) starts it afresh and sets it aside as checkpoint.msgpack.damaged")


# 7. Task definitions are checked when a task is made, before anything is allocated.

@dataclasses.dataclass(frozen=True, eq=False)
class Untouchable(Task):
    def evaluate(self, actions, key):
        raise AssertionError("evaluate must not be traced before the task's definition is checked")


@pytest.mark.parametrize(("bounds", "match"), [
    (((0.0,), (1.0,), (1.0, 0.0), (0.0, 1.0)), r"the behavior box is empty in dimension 0 \(behavior_low\[0\]=1.0 "
                                                r"is not below behavior_high\[0\]=0.0\)"),
    (((0.0,), (1.0,), (0.5, 0.0), (0.5, 1.0)), "the behavior box is empty in dimension 0"),
    (((0.0,), (1.0,), (0.0, 0.0), (1.0,)), "behavior_low has 2 dimensions and behavior_high 1"),
    (((0.0,), (1.0,), (0.0, float("nan")), (1.0, 1.0)), r"behavior_low=\(0.0, nan\) is invalid: every bound must be "
                                                        "finite"),
    (((0.0, 2.0), (1.0, 1.0), (0.0, 0.0), (1.0, 1.0)), "the action box is empty in dimension 1"),
    (((), (), (0.0, 0.0), (1.0, 1.0)), r"action_low=\(\) is invalid: expected a non-empty tuple of numbers"),
    (((0.0,), (1.0,), (0.0,) * 9, (1.0,) * 9), r"a behavior space of 9 dimensions is not supported \(supported: 1 to"),
])
def test_a_bad_task_definition_is_refused_before_anything_is_traced(bounds, match, registered):
    with pytest.raises(ValueError, match=match):
        Config(task=Untouchable(*bounds))
    registered("untouchable_test", lambda: Untouchable(*bounds))
    with pytest.raises(ValueError, match="task 'untouchable_test': " + match):
        registry.make("untouchable_test")


def test_a_9d_behavior_box_is_refused_before_anything_is_allocated():
    start = time.perf_counter()
    with pytest.raises(ValueError, match=f"supported: {BEHAVIOR_DIMS[0]} to {BEHAVIOR_DIMS[-1]}"):
        Config(task=Untouchable((0.0,), (1.0,), (0.0,) * 9, (1.0,) * 9), coverage_resolution=256)
    assert time.perf_counter() - start < 1.0  # a 256^9 grid could not be made at all


def test_the_built_in_tasks_pass_their_own_checks():
    for name in ("obstacle2d", "object2d", "push_cube"):
        assert isinstance(registry.make(name), Task)  # make checks them


# 8. Smaller promises.

def test_plot_and_adapt_of_a_mistyped_folder_do_not_create_it(tmp_path, refused):
    for command in ("plot", "adapt"):
        refused([command, str(tmp_path / "typo")], f"{str(tmp_path / 'typo')!r} does not exist")
    assert not (tmp_path / "typo").exists()


def test_adapt_without_mqd_runs_is_an_error(tmp_path, refused):
    cli.main(sweep_argv(tmp_path))
    refused(["adapt", str(tmp_path)], "holds no M-QD runs to adapt: run `mqd sweep --algorithms mqd")


@pytest.mark.parametrize("seed", [2**32, 2**32 + 7, -1])
def test_seeds_that_would_share_a_key_are_refused(seed, tmp_path, refused):
    refused(["run", *TINY, "--seed", str(seed), "--out", str(tmp_path)], f"--seed {seed} is invalid")
    assert not (tmp_path / "metrics.json").exists()


def test_tables_and_figures_are_written_whole(tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    table, figure = tmp_path / "table1.md", tmp_path / "fig.png"
    table.write_text("the old table\n")
    figure.write_bytes(b"the old figure")

    def disk_full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", disk_full)
    with pytest.raises(OSError):
        tables.write_markdown(["the new table"], str(table))
    plt = plots.pyplot()
    with pytest.raises(OSError):
        plots.save(plt.figure(), str(figure))
    assert table.read_text() == "the old table\n" and figure.read_bytes() == b"the old figure"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig.png", "table1.md"]  # no half-written leftovers


def test_tell_refuses_the_candidates_of_an_older_ask():
    cfg = Config(population_size=4, capacity=16)
    state = mqd_jax.init(jax.random.PRNGKey(0), cfg)
    candidates = mqd_jax.ask(state, cfg)
    b, q, v = registry.make("obstacle2d").evaluate(candidates.actions, candidates.key)
    state, _ = mqd_jax.tell(state, candidates, b, q, v, cfg)
    with pytest.raises(ValueError, match="asked at generation 0, the state is at generation 1"):
        mqd_jax.tell(state, candidates, b, q, v, cfg)
    # Inside the caller's own jit the generations are traced; the fused generation is unchanged.
    fused = jax.jit(lambda s: mqd_jax.generation(s, cfg, cfg.params())[0])(state)
    assert int(fused.generation) == 2


def test_the_design_document_names_the_checkpoint_format_the_code_writes():
    design = (ROOT / "docs" / "design.md").read_text()
    assert set(re.findall(r"checkpoint\.py`, format (\d+)", design)) == {str(checkpoint.FORMAT)}


def test_json_checksums_survive_what_json_does_to_keys_and_numbers(tmp_path):
    path = str(tmp_path / "x.json")
    payload = {"b": {10: 1.0, 9: float("nan")}, "a": (np.float32(0.1), np.int64(3)), "c": 1e-320}
    folders.write_json(path, payload)
    assert files.read_json(path, "") == {"b": {"10": 1.0, "9": None}, "a": [float(np.float32(0.1)), 3],
                                           "c": 1e-320}
    with pytest.raises(ValueError, match="the key 'sha256' is the file's checksum"):
        folders.write_json(path, {"sha256": 1})
    assert json.loads(pathlib.Path(path).read_text())["sha256"]

