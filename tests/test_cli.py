import argparse
import dataclasses
import json

import jax
import numpy as np
import pytest

from mqd_jax import Config, run_mqd
from mqd_jax.experiment import cli, flags


def test_mqd_run_in_chunks_equals_one_run(tmp_path, capsys):
    cli.main(["run", "--generations", "6", "--population", "8", "--capacity", "64", "--archive-capacity", "16",
              "--chunk", "4", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert out.count("generation ") == 2 and "done: coverage" in out
    metrics = json.loads((tmp_path / "metrics.json").read_text())["metrics"]
    _, want = run_mqd(jax.random.PRNGKey(0), Config(max_generations=6, population_size=8, capacity=64,
                                                                archive_capacity=16))
    np.testing.assert_array_equal(metrics["repertoire_size"], want["repertoire_size"])
    np.testing.assert_array_equal(metrics["coverage"], want["coverage"])
    rep = np.load(tmp_path / "repertoire.npz")
    assert len(rep["behaviors"]) == metrics["repertoire_size"][-1]


def test_mqd_run_mqd_writes_strict_json_with_null_for_untrained_generations(tmp_path, capsys):
    cli.main(["run", "--algorithm", "mqd", "--generations", "4", "--population", "8", "--capacity", "64",
              "--archive-capacity", "16", "--algorithm-option", "warmup_samples=30", "num_batches=5", "--out",
              str(tmp_path)])
    text = (tmp_path / "metrics.json").read_text()
    assert "NaN" not in text
    metrics = json.loads(text)["metrics"]
    # Trained at the end of generation 4 only (32 >= 30 evaluations).
    assert metrics["model_loss"][:3] == [None] * 3 and metrics["model_loss"][3] > 0
    assert all(x is not None for x in metrics["prediction_error"])
    assert "discarded      0" in capsys.readouterr().out


def test_mqd_run_resumes_its_checkpoint_and_refuses_another_config(tmp_path, capsys):
    argv = ["run", "--generations", "6", "--population", "8", "--capacity", "64", "--archive-capacity", "16",
            "--chunk", "3", "--out", str(tmp_path)]
    cli.main(argv)
    first = json.loads((tmp_path / "metrics.json").read_text())
    capsys.readouterr()
    cli.main([*argv, "--resume"])  # already complete: nothing to run, same results
    out = capsys.readouterr().out
    assert "resuming at generation 6 of 6" in out and "compiling" not in out
    assert not any(line.startswith("generation") for line in out.splitlines())
    assert json.loads((tmp_path / "metrics.json").read_text())["metrics"] == first["metrics"]
    with pytest.raises(SystemExit):
        cli.main([*argv[:-2], "--t-dist", "0.01", "--out", str(tmp_path), "--resume"])
    err = capsys.readouterr().err
    assert "its own config and seed, which the flags given contradict (t_dist: saved 0.02, now 0.01)" in err
    with pytest.raises(SystemExit):
        cli.main([*argv[:-2], "--t-dist", "0.01", "--out", str(tmp_path)])
    assert "another run (" in (err := capsys.readouterr().err) and "t_dist: saved 0.02, now 0.01" in err


def test_mqd_run_warns_when_niches_are_dropped(tmp_path):
    dropped = r"7 new niches did not fit in the repertoire: raise capacity \(--capacity\) above 10"
    with pytest.warns(UserWarning, match=dropped):
        cli.main(["run", "--generations", "3", "--population", "10", "--capacity", "10", "--out", str(tmp_path)])


def test_every_config_field_has_a_flag_options_are_named_and_presets_apply():
    parser = argparse.ArgumentParser()
    flags.add_config_flags(parser)
    args = parser.parse_args(["--preset", "paper-robot", "--algorithm-option", "t_nov=0.05", "budgeted=True",
                              "--algorithm", "mqd-paper", "--population", "50", "-O", "anchor_free=x"])
    assert args.algorithm_options == [("t_nov", 0.05), ("budgeted", True), ("anchor_free", "x")]
    args.algorithm_options.pop()
    cfg = flags.config_from_flags(args)
    assert cfg == Config.paper_robot(algorithm_options={"t_nov": 0.05, "budgeted": True}, algorithm="mqd-paper",
                                     population_size=50)
    assert cfg.options["hidden_size"] == 64  # Table II's robot column
    assert flags.config_from_flags(parser.parse_args([])) == Config()
    assert flags.config_from_flags(parser.parse_args([]), defaults={"max_generations": 100}) == \
        Config(max_generations=100)
    # `mqd sweep`'s preset "auto" is the paper's column for each task; each algorithm takes the options it has.
    auto = argparse.ArgumentParser()
    flags.add_config_flags(auto, skip=flags.PER_TASK, preset="auto")
    args = auto.parse_args(["--t-dist", "0.01", "-O", "t_nov=0.05"])
    assert flags.config_from_flags(args, task="place", algorithm="qd") == Config.paper_robot(task="place", t_dist=0.01)
    assert flags.config_from_flags(args, task="object2d", algorithm="mqd-paper") == Config.paper_2d(
        task="object2d", t_dist=0.01, algorithm="mqd-paper", algorithm_options={"t_nov": 0.05})
    with pytest.raises(SystemExit):
        auto.parse_args(["--task", "place"])  # per task: --tasks
    for field in dataclasses.fields(Config):
        if field.name == "algorithm_options":  # --algorithm-option NAME=VALUE, above
            continue
        value = getattr(Config(), field.name)
        assert getattr(parser.parse_args(["--" + field.name.replace("_", "-"), str(value)]), field.name) == value


def test_mqd_run_rejects_bad_config(tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli.main(["run", "--population", "0", "--out", str(tmp_path)])
    assert "Config.population_size=0" in capsys.readouterr().err
