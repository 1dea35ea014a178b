import json

import jax
import numpy as np
import pytest

from mqd_jax import Config, cli, run_mqd


def test_mqd_run_in_chunks_equals_one_run(tmp_path, capsys):
    cli.main(["run", "--generations", "6", "--population", "8", "--capacity", "64", "--chunk", "4",
              "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert out.count("generation ") == 2 and "done: coverage" in out
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    _, want = run_mqd(jax.random.PRNGKey(0), Config(max_generations=6, population_size=8, capacity=64))
    np.testing.assert_array_equal(metrics["repertoire_size"], want["repertoire_size"])
    np.testing.assert_allclose(metrics["coverage"], want["coverage"], rtol=1e-6)
    rep = np.load(tmp_path / "repertoire.npz")
    assert len(rep["behaviors"]) == metrics["repertoire_size"][-1]


def test_mqd_run_warns_when_niches_are_dropped(tmp_path):
    with pytest.warns(UserWarning, match="raise --capacity above 10"):
        cli.main(["run", "--generations", "3", "--population", "10", "--capacity", "10", "--out", str(tmp_path)])


def test_mqd_run_rejects_bad_config(tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli.main(["run", "--population", "0", "--out", str(tmp_path)])
    assert "Config.population_size=0" in capsys.readouterr().err
