"""Every preset repeats, bit for bit, the runs saved from mqd-jax 0.9.0 (`reference_runs.py`).

Every array of the final state and every metric must be equal. M-QD's trained floats may round otherwise on
another CPU model (and its choices follow them), so M-QD's runs are compared on the CPU model the arrays were
saved on (this project's machines) and skipped, saying so, on another; QD's and RANDOM's everywhere.
"""

import json

import numpy as np
import pytest
import reference_runs


@pytest.fixture(scope="module")
def saved():
    with np.load(reference_runs.PATH) as f:
        return {k: f[k] for k in f.files}


@pytest.mark.parametrize("algorithm", reference_runs.ALGORITHMS)
@pytest.mark.parametrize("task", reference_runs.TASKS)
def test_a_run_repeats_the_saved_one_bit_for_bit(task, algorithm, saved):
    cpu = json.loads(str(saved["about"]))["cpu"]
    if algorithm.startswith("mqd") and cpu != reference_runs.cpu_model():
        pytest.skip(f"M-QD's saved runs were made on {cpu}, this is {reference_runs.cpu_model()}")
    # 0.10 moved the model emitter's model, rollouts, anchoring errors and validity into its surrogate's state.
    now = {name.replace(".emitter.surrogate.", ".emitter."): x
           for name, x in reference_runs.arrays(task, algorithm).items()}
    prefix = f"{task}/{algorithm}/"
    before = {k[len(prefix):]: v for k, v in saved.items() if k.startswith(prefix)}
    # 0.12 added the standard metrics max_quality and qd_score (checked against their definitions in test_run.py).
    assert sorted(now) == sorted([*before, "metrics.max_quality", "metrics.qd_score"])
    now = {name: x for name, x in now.items() if name in before}
    for name, x in now.items():
        assert x.dtype == before[name].dtype and x.shape == before[name].shape, name
        if algorithm == "mqd-paper" and np.issubdtype(x.dtype, np.floating) and not name.startswith("metrics."):
            # 0.12's generation program (two more metrics, coverage in any dimension) is compiled with other
            # roundings in the paper's filter's model training: one weight 1e-10 apart on PushCube, two of the
            # repertoire's 576 action entries 2e-7 apart on 2D Obstacle. Every choice (every integer and boolean
            # array), every metric and the other presets stay bit for bit the same.
            np.testing.assert_allclose(x, before[name], rtol=1e-5, atol=1e-6, err_msg=name)
        else:
            np.testing.assert_array_equal(x, before[name], err_msg=name)
