"""Saved runs that a refactor must repeat bit for bit: every preset on 2D Obstacle and PushCube.

    python tests/reference_runs.py [PATH]   # writes PATH, else tests/data/reference_runs.npz (the tests' XLA flags)

`test_reference_runs.py` runs the same configs and compares every array of the final state and every metric
with the saved ones. `reference_runs.npz` was written from the code of mqd-jax 0.9.0 on an AMD EPYC without
AVX-512; `reference_runs_avx512.npz` from the code of 0.12.0 (git 94c1f0c; "+dirty": this file's output path and
CPU label only) on an AMD EPYC with AVX-512, whose vector units round C MuJoCo's physics and M-QD's training
otherwise; `reference_runs_vp2intersect.npz` from the code of 0.16.0 (git f8099be; "+dirty": the [trust-4]
tests copied into that checkout only) on an AMD EPYC whose AVX-512 has VP2INTERSECT (a later generation, reported
under the same model name, whose PushCube runs differ from the previous one's in the fifth digit);
`reference_runs_vaes.npz` from the code of 0.22.0 (git 00f072e) on an AMD EPYC without AVX-512 but with VAES
(family 25: its PushCube runs and one ulp of "mqd"'s metrics differ from the first file's). Each file saves
its git revision and the CPU (`cpu_model`) beside the arrays; the test compares with the file of this machine's
CPU: a change that alters a run's numbers shows here first.
"""

from __future__ import annotations

import json
import os
import pathlib
import sys

# The tests' XLA flags (conftest.py): the saved arrays are what the tests compute.
os.environ.setdefault("XLA_FLAGS", "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false")

import jax
import numpy as np

from mqd_jax import Config, run_mqd
from mqd_jax.core import registry
from mqd_jax.experiment.provenance import cpu_model, provenance

PATH = pathlib.Path(__file__).resolve().parent / "data" / "reference_runs.npz"
# The saved runs, of the CPUs they were made on.
PATHS = (PATH, PATH.with_name("reference_runs_avx512.npz"), PATH.with_name("reference_runs_vp2intersect.npz"),
         PATH.with_name("reference_runs_vaes.npz"))
ALGORITHMS = ("qd", "random", "mqd", "mqd-paper")
TASKS = ("obstacle2d", "push_cube")


def config(task: str, algorithm: str) -> Config:
    """A tiny run: 3 generations of 8 candidates; M-QD's model filters from the second generation. (0.9.0 saved
    them from `Config(..., warmup_samples=8, num_batches=2, t_nov=0.0, t_qua=0.0)`: the same runs.)"""
    made = registry.make(task, backend="mujoco") if task == "push_cube" else task
    # 0.11 made "mqd"'s model take the task's features and a gate; 0.9.0's "mqd" had neither.
    options = {"mqd": dict(warmup_samples=8, num_batches=2, features=False, gate=False),
               "mqd-paper": dict(warmup_samples=8, num_batches=2, t_nov=0.0, t_qua=0.0)}.get(algorithm, {})
    return Config(task=made, algorithm=algorithm, max_generations=3, population_size=8, capacity=64,
                  archive_capacity=32, algorithm_options=options)


def arrays(task: str, algorithm: str) -> dict[str, np.ndarray]:
    """{name: array}: every leaf of the final state (by its path) and every metric of a run of `config`."""
    state, metrics = run_mqd(jax.random.PRNGKey(0), config(task, algorithm))
    leaves = jax.tree_util.tree_flatten_with_path(jax.device_get(state))[0]
    found = {f"state{jax.tree_util.keystr(path)}": np.asarray(x) for path, x in leaves}
    return {**found, **{f"metrics.{k}": np.asarray(v) for k, v in metrics.items()}}


def main() -> None:
    saved = {f"{task}/{algorithm}/{name}": x for task in TASKS for algorithm in ALGORITHMS
             for name, x in arrays(task, algorithm).items()}
    about = {"cpu": cpu_model(), "provenance": provenance()}
    path = pathlib.Path(sys.argv[1]) if len(sys.argv) > 1 else PATH
    path.parent.mkdir(exist_ok=True)
    np.savez_compressed(path, about=np.asarray(json.dumps(about)), **saved)
    print(f"wrote {path}: {len(saved)} arrays, {path.stat().st_size} bytes")


if __name__ == "__main__":
    main()
