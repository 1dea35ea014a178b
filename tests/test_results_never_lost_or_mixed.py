"""Results are never lost or mixed: one test per case, and the command line's small promises."""

import dataclasses
import hashlib
import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

import mqd_jax
from mqd_jax import Config, adapt, run_mqd
from mqd_jax.core import diagnostics, registry
from mqd_jax.core.config import check_params
from mqd_jax.core.state import init
from mqd_jax.experiment import checkpoint, cli, files, folders, manifest, provenance, results
from mqd_jax.experiment.sweep import grid, param_names, run_batch, seed_keys


def digest(folder):
    """{file name: SHA-256} of every file in `folder` (to show that nothing changed)."""
    return {f: hashlib.sha256((folder / f).read_bytes()).hexdigest() for f in sorted(os.listdir(folder))}


# Case 1: a run folder belongs to one config and seed.

def test_run_folder_refuses_another_config_and_keeps_the_first_run(tmp_path, capsys, refused, tiny_mqd_flags,
                                                                   tiny_flags):
    out = str(tmp_path)
    cli.main(["run", *tiny_mqd_flags, "--algorithm", "mqd", "--out", out])
    before = digest(tmp_path)
    err = refused(["run", *tiny_flags, "--generations", "2", "--algorithm", "random", "--out", out],
                  "it holds results of another run")
    assert "algorithm: saved 'mqd', now 'random'" in err and "max_generations: saved 3, now 2" in err
    assert err.startswith("mqd run: error:") and err.count("\n") == 1  # one line, not the usage text
    assert digest(tmp_path) == before
    refused(["run", *tiny_mqd_flags, "--algorithm", "mqd", "--seed", "1", "--out", out], "seed: saved 0, now 1")
    # The first run is still whole: it resumes (already complete: nothing to run).
    cli.main(["run", *tiny_mqd_flags, "--algorithm", "mqd", "--out", out, "--resume"])
    assert json.loads((tmp_path / "metrics.json").read_text())["config"]["algorithm"] == "mqd"
    # --overwrite is the way out.
    cli.main(["run", *tiny_flags, "--generations", "2", "--algorithm", "random", "--out", out, "--overwrite"])
    assert "--overwrite: removed" in capsys.readouterr().out
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["config"] == Config(algorithm="random", max_generations=2, population_size=8, capacity=64,
                                     archive_capacity=16).to_dict()


def test_every_run_file_records_config_seed_versions_and_revision(tmp_path, tiny_flags):
    cli.main(["run", *tiny_flags, "--seed", "7", "--out", str(tmp_path)])
    cfg = Config(max_generations=3, population_size=8, capacity=64, archive_capacity=16).to_dict()
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["config"] == cfg and saved["seed"] == 7
    assert saved["key"] == np.asarray(jax.random.PRNGKey(7)).tolist()
    assert saved["provenance"]["versions"]["jax"] == jax.__version__
    assert saved["implementation"] == {"mqd_jax": mqd_jax.__version__, "task": registry.source("obstacle2d")}
    assert saved["provenance"]["git"]  # this checkout's commit
    meta = json.loads(str(np.load(tmp_path / "repertoire.npz")["meta"]))
    assert meta["config"] == cfg and meta["seed"] == 7 and meta["provenance"] == saved["provenance"]
    if importlib.util.find_spec("matplotlib"):  # the figure needs the optional plot extra
        from PIL import Image

        assert json.loads(Image.open(tmp_path / "run.png").text["Description"])["config"] == cfg
    owner = json.loads((tmp_path / manifest.MANIFEST).read_text())
    assert owner["kind"] == "run" and owner["identity"] == {"config": cfg, "seed": 7}


def test_the_machine_names_its_cpu_and_what_makes_it_round_otherwise(tmp_path, monkeypatch):
    def cpu(flags, name="model name\t: AMD EPYC"):
        path = tmp_path / "cpuinfo"
        path.write_text(f"processor\t: 0\n{name}\nflags\t\t: fpu sse2 {flags}\n\nprocessor\t: 1\n")
        return provenance.cpu_model(str(path))

    assert cpu("avx2 vaes avx512f avx512_vp2intersect") == "AMD EPYC with AVX-512 and VP2INTERSECT"
    assert cpu("avx2 avx512f avx512_bf16") == "AMD EPYC with AVX-512"
    assert cpu("avx2 vaes") == "AMD EPYC with VAES"
    assert cpu("avx2") == "AMD EPYC"
    monkeypatch.setattr(provenance.platform, "processor", lambda: "")
    assert cpu("avx512f", name="") == provenance.platform.machine()  # no model name: the architecture
    assert provenance.cpu_model(str(tmp_path / "absent")) == provenance.platform.machine()
    monkeypatch.setattr(provenance, "cpu_model", lambda: "Some CPU with AVX-512")
    assert provenance.machine().startswith(f"{provenance.platform.machine()} (Some CPU with AVX-512), "
                                           f"{os.cpu_count()} CPU cores, jax {jax.__version__}")


def test_results_of_an_older_version_without_a_manifest_are_not_replaced_silently(tmp_path, capsys, refused,
                                                                                 tiny_flags):
    old = '{"config": {}, "provenance": {"versions": {"mqd-jax": "0.8.0"}}}'  # an older mqd-jax's, no checksum
    (tmp_path / "metrics.json").write_text(old)
    refused(["run", *tiny_flags, "--out", str(tmp_path)], "results without a valid manifest (metrics.json")
    assert (tmp_path / "metrics.json").read_text() == old
    # A user's own file of the same name is not ours: refused, even with --overwrite, and kept.
    (tmp_path / "metrics.json").write_text("{}")
    refused(["run", *tiny_flags, "--out", str(tmp_path), "--overwrite"], "metrics.json is not written by mqd-jax")
    assert (tmp_path / "metrics.json").read_text() == "{}"


# Case 2: a sweep folder never mixes configs, and derived files follow their inputs.

def sweep(out, *flags):
    cli.main(["sweep", "--tasks", "obstacle2d", "--generations", "3", "--population", "8", "--capacity", "64",
              "--archive-capacity", "16", "--out", str(out), *flags])


def test_sweep_refuses_a_batch_of_another_config_before_running_anything(tmp_path, capsys, refused, tiny_flags):
    sweep(tmp_path, "--algorithms", "qd", "random", "--seeds", "3")
    before = digest(tmp_path)
    capsys.readouterr()
    err = refused(["sweep", "--tasks", "obstacle2d", "--algorithms", "random", "--seeds", "2", *tiny_flags,
                   "--generations", "2", "--out", str(tmp_path)], "refused")
    assert "obstacle2d_qd differs (max_generations: saved 3, now 2, 3 other seed keys, now 2)" in err
    assert "generation" not in capsys.readouterr().out and digest(tmp_path) == before
    # With --overwrite, both clashing batches go: the folder holds only comparable runs.
    sweep(tmp_path, "--algorithms", "random", "--seeds", "2", "--generations", "2", "--overwrite")
    runs = results.load_runs(str(tmp_path))
    assert list(runs["obstacle2d"]) == ["random"] and runs["obstacle2d"]["random"].metrics["coverage"].shape == (2, 2)
    assert "Seeds per task: 2;" in (tmp_path / "table1.md").read_text()


def test_tables_refuse_a_folder_whose_batches_were_mixed_by_hand(tmp_path):
    sweep(tmp_path, "--algorithms", "qd", "random", "--seeds", "2")
    # Not the paper's settings, so no paper values beside them, and the table says why.
    table = (tmp_path / "table1.md").read_text()
    assert "(paper" not in table and "shown only beside runs with Table II's settings" in table
    path = str(tmp_path / "obstacle2d_random.json")
    saved = files.read_json(path, "")
    saved["config"]["t_dist"] = 0.03
    folders.write_json(path, saved)  # a sound file of other runs, as another sweep would write it
    with pytest.raises(ValueError, match=r"mixes runs that cannot be compared.*t_dist: saved 0\.03, now 0\.02"):
        results.load_runs(str(tmp_path))


def test_batches_need_agree_only_on_the_options_both_presets_take(tmp_path):
    """A QD batch sits beside M-QD batches of any model settings (QD takes none); two model presets must agree on
    the options both take (hidden size), not on those one of them has alone (ensemble size, t_nov)."""
    sweep(tmp_path, "--algorithms", "qd", "--seeds", "2")
    qd = files.read_json(str(tmp_path / "obstacle2d_qd.json"), "")
    cfg = Config(max_generations=3, population_size=8, capacity=64, archive_capacity=16)
    checkpoint.save(str(tmp_path / "obstacle2d_mqd.msgpack"), init(jax.random.PRNGKey(0), cfg), {}, cfg,
                    jax.random.PRNGKey(0))

    def add(algorithm, **options):
        config = Config.from_dict(qd["config"])
        made = Config(task=config.task, algorithm=algorithm, algorithm_options=options, max_generations=3,
                      population_size=8, capacity=64, archive_capacity=16)
        folders.write_json(str(tmp_path / f"obstacle2d_{algorithm}.json"), {**qd, "config": made.to_dict()})
        shutil.copy(tmp_path / "obstacle2d_qd.npz", tmp_path / f"obstacle2d_{algorithm}.npz")

    add("mqd", ensemble_size=4, hidden_size=64, warmup_samples=8)
    add("mqd-paper", hidden_size=64, t_nov=0.5, warmup_samples=8)
    assert list(results.load_runs(str(tmp_path))["obstacle2d"]) == ["mqd", "mqd-paper", "qd"]
    add("mqd-paper", hidden_size=32, warmup_samples=8)
    with pytest.raises(ValueError, match=r"cannot be compared.*_mqd differs \(algorithm_options.hidden_size: saved "
                                         r"64, now 32\)"):
        results.load_runs(str(tmp_path))
    add("mqd-paper", hidden_size=64, warmup_samples=8, iso_sigma=0.03)  # QD takes iso_sigma too
    with pytest.raises(ValueError, match=r"cannot be compared.*algorithm_options.iso_sigma: saved 0.02, now 0.03"):
        results.load_runs(str(tmp_path))


def test_adaptation_of_replaced_mqd_runs_is_left_out_and_tables_are_remade(tmp_path, capsys):
    mqd = ["--algorithms", "mqd", "--seeds", "2", "--algorithm-option", "warmup_samples=8", "num_batches=2"]
    sweep(tmp_path, *mqd)
    cli.main(["adapt", str(tmp_path), "--goals", "3"])
    assert (tmp_path / "adaptation.md").exists()
    entry = json.loads((tmp_path / "adaptation.json").read_text())["obstacle2d"]
    assert entry["config"]["algorithm_options"]["optimism"] == 1.0
    assert entry["provenance"]["versions"]["jax"] == jax.__version__
    sweep(tmp_path, *mqd, "optimism=0.5", "--overwrite")  # other M-QD runs: the adaptation results are stale
    out = capsys.readouterr().out
    assert "left out the adaptation results of obstacle2d" in out
    assert not (tmp_path / "adaptation.md").exists() and not (tmp_path / "fig3_adaptation_error.png").exists()
    kept = json.loads((tmp_path / "adaptation.json").read_text())["obstacle2d"]  # kept, not used
    assert kept["config"]["algorithm_options"]["optimism"] == 1.0
    found, stale = results.adaptation(str(tmp_path))
    assert found == {} and stale == ["obstacle2d"]


def test_saving_a_batch_removes_the_tables_made_before_it_and_only_those(tmp_path):
    made = ["table1.md", "adaptation.md", "fig2_obstacle2d.png", "fig3_adaptation_error.png"]
    with folders.lock(str(tmp_path)):
        folders.claim(str(tmp_path), "sweep", {}, results.patterns(), False)
        for name in made:
            folders.write_atomically(str(tmp_path / name), b"made from earlier results")
    (tmp_path / "fig2_mine.png").write_text("the user's, named like a figure")
    cfg = Config(max_generations=3, population_size=8, capacity=64, archive_capacity=16, algorithm="random")
    keys = np.asarray(seed_keys(2))
    states, metrics = run_batch(cfg, keys)
    results.save_runs(str(tmp_path), cfg, keys, states, metrics, 1.0)
    assert not any((tmp_path / name).exists() for name in made)
    assert (tmp_path / "obstacle2d_random.json").exists() and (tmp_path / "fig2_mine.png").exists()


# Case 3: one writer at a time.

HOLD_LOCK = textwrap.dedent("""
    import sys, time
    from mqd_jax.experiment import files, folders, manifest
    with folders.lock(sys.argv[1]):
        print("locked", flush=True)
        time.sleep(600)
""")


def test_a_second_writer_is_refused_and_a_killed_writer_leaves_no_lock(tmp_path, capsys, refused, tiny_flags):
    holder = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        refused(["run", *tiny_flags, "--out", str(tmp_path)],
                f"is being written by another mqd process (pid {holder.pid})")
        refused(["sweep", "--tasks", "obstacle2d", "--algorithms", "qd", *tiny_flags, "--out", str(tmp_path)],
                "another mqd process")
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    with folders.lock(str(tmp_path)):  # the kernel released the killed holder's lock
        pass


def test_leftover_temporary_files_of_a_killed_writer_are_removed(tmp_path, capsys):
    with folders.lock(str(tmp_path)):
        folders.claim(str(tmp_path), "run", {"seed": 0}, ("metrics.json",), False)
        folders.write_json(str(tmp_path / "metrics.json"), {"a": 1})
    (tmp_path / "metrics.json.abc12345.mqdtmp").write_bytes(b"half a file")
    (tmp_path / "notes.txt.abc12345.mqdtmp").write_bytes(b"a user's file, named like a temporary one")
    with folders.lock(str(tmp_path)) as removed:
        assert [os.path.basename(p) for p in removed] == ["metrics.json.abc12345.mqdtmp"]
    assert [p.name for p in tmp_path.glob("*.mqdtmp")] == ["notes.txt.abc12345.mqdtmp"]


# Case 4: runtime parameters, states and checkpoints are checked.

@pytest.mark.parametrize(("algorithm", "name", "value", "match"), [
    ("qd", "t_dist", np.nan, "Params.t_dist=nan"), ("qd", "t_dist", 0.05, "Params.t_dist=0.05.* and <= 0.02"),
    ("qd", "emitter.iso_sigma", np.nan, "IsoLine.params.iso_sigma=nan"),
    ("mqd-paper", "emitter.surrogate.learning_rate", 0.0, "Surrogate.params.learning_rate=0.0"),
    ("mqd-paper", "emitter.acquisition.t_qua", np.inf, "Threshold.params.t_qua=inf"),
    ("mqd-paper", "emitter.acquisition.t_nov", -0.1, "Threshold.params.t_nov=-0.1")])
def test_invalid_concrete_params_are_refused_naming_the_part_and_the_field(algorithm, name, value, match):
    cfg = Config(algorithm=algorithm, max_generations=2, population_size=8, capacity=64,
                 algorithm_options={} if algorithm == "qd" else {"warmup_samples": 8})
    leaves, structure = jax.tree.flatten(cfg.params())
    at = param_names(cfg.params()).index(name)
    params = jax.tree.unflatten(structure, [np.float32(value) if i == at else x for i, x in enumerate(leaves)])
    with pytest.raises(ValueError, match=match):
        run_mqd(jax.random.PRNGKey(0), cfg, params)
    with pytest.raises(ValueError, match=match):  # one bad member of a batch is enough
        grid(cfg, {name: [float(leaves[at]), value]}, seeds=1)


def test_params_check_skips_traced_values_and_accepts_the_configs_own():
    cfg = Config()
    check_params(cfg.params(), cfg)
    jax.jit(lambda t: check_params(cfg.params().replace(t_dist=t), cfg) or t)(np.float32(np.nan))  # traced: skipped


def test_adapt_refuses_a_state_of_another_task():
    cfg = Config(max_generations=2, population_size=8, capacity=64, archive_capacity=16)
    state, _ = run_mqd(jax.random.PRNGKey(0), cfg)
    with pytest.raises(ValueError, match=r"does not belong to this config.*task 'object2d'"):
        adapt(state, np.zeros((2, 2), np.float32), jax.random.PRNGKey(1), dataclasses.replace(cfg, task="object2d"),
              "nearest")


def test_a_checkpoint_altered_in_place_is_refused(tmp_path):
    cfg = Config(max_generations=2, population_size=8, capacity=64, archive_capacity=16)
    key, path = jax.random.PRNGKey(0), str(tmp_path / "c.msgpack")
    checkpoint.run_with_checkpoints(key, cfg, path, every=1)
    data = bytearray((tmp_path / "c.msgpack").read_bytes())
    checkpoint.load(path, cfg, key)  # intact: loads
    data[len(data) // 2] ^= 1  # one bit, inside the saved arrays
    (tmp_path / "c.msgpack").write_bytes(bytes(data))
    with pytest.raises(ValueError, match="checksum does not match"):
        checkpoint.load(path, cfg, key)


# Case 5: what goes wrong without an error is said, with counts.

@pytest.mark.parametrize(("changes", "match"), [
    ({"scale": 0.5}, r"valid rollouts returned a quality outside the task's quality_range \(-6.3, 0.0\)"),
    ({"offset": 0.3}, "valid rollouts ended outside the behavior box"),
    ({"valid": False}, "all 24 rollouts were invalid")])
def test_unreliable_runs_warn_once_with_counts(changes, match):
    import plugin_tasks

    cfg = Config(task=plugin_tasks.make_reach(**changes), algorithm="mqd", max_generations=3, population_size=8,
                 capacity=64, archive_capacity=16, algorithm_options=dict(warmup_samples=8, num_batches=2))
    with pytest.warns(diagnostics.RunWarning, match=match) as caught:
        _, metrics = run_mqd(jax.random.PRNGKey(0), cfg)
    caught = [w for w in caught if w.category is diagnostics.RunWarning]
    assert len(caught) == 1
    counts = {k: int(np.sum(metrics[k])) for k in ("out_of_range", "out_of_box", "invalid")}
    key = {"scale": "out_of_range", "offset": "out_of_box", "valid": "invalid"}[next(iter(changes))]
    assert counts[key] > 0 and str(counts[key]) in str(caught[0].message)
    assert all(v == 0 for k, v in counts.items() if k != key)


def test_a_sound_run_does_not_warn():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", diagnostics.RunWarning)
        run_mqd(jax.random.PRNGKey(0), Config(max_generations=2, population_size=8, capacity=64, archive_capacity=16))
