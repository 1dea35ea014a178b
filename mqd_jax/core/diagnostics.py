"""Host-side checks of a run's metrics: what went wrong without an error, said once per run with counts.

`problems(metrics, cfg)` lists them; `warn(metrics, cfg)` emits each as a
`RunWarning`. `run_mqd`, `checkpoint.run_with_checkpoints`, `sweep.run_batch`
and the `mqd` command line call `warn` on their results; an ask/tell loop can
call it on its stacked metrics. The counts come from the per-generation metrics
(see `run_mqd`): `dropped_full`, `out_of_range`, `out_of_box`, `invalid`,
`evaluations`; and the emitter's own (`Emitter.problems`: M-QD's model predicting NaN).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping

import numpy as np

from mqd_jax.core.config import Config
from mqd_jax.core.task import Task


class RunWarning(UserWarning):
    """A run finished, but part of what it did is unreliable (see `problems`)."""


def problems(metrics: Mapping[str, np.ndarray], cfg: Config, task: Task) -> list[str]:
    """One message per problem in `metrics` (arrays [G] of one run or [R, G] of a batch; totals over all)."""
    total = {name: int(np.sum(np.asarray(metrics[name]))) for name in
             ("dropped_full", "out_of_range", "out_of_box", "invalid", "evaluations")}
    valid = total["evaluations"] - total["invalid"]
    label = f"{cfg.task_name} {cfg.algorithm_name}: "
    found = []
    if total["evaluations"] and not valid:
        found.append(f"{label}all {total['evaluations']} rollouts were invalid (valid=False or a non-finite "
                     "behavior or quality): the repertoire stayed empty")
    if total["dropped_full"]:
        found.append(f"{label}{total['dropped_full']} new niches did not fit in the repertoire: raise capacity "
                     f"(--capacity) above {cfg.capacity}")
    if total["out_of_range"]:
        found.append(f"{label}{total['out_of_range']} of {valid} valid rollouts returned a quality outside the "
                     f"task's quality_range {task.quality_range}: M-QD's model cannot predict such qualities "
                     "(its filter and adaptation degrade); widen Task.quality_range")
    if total["out_of_box"]:
        found.append(f"{label}{total['out_of_box']} of {valid} valid rollouts ended outside the behavior box "
                     f"{task.behavior_low}-{task.behavior_high}: coverage counts only the box and M-QD's model "
                     "cannot predict behaviors outside it; widen the task's behavior box")
    return found + [label + message for message in cfg.emitter.problems(metrics)]


def warn(metrics: Mapping[str, np.ndarray], cfg: Config, task: Task) -> None:
    """Emits each of `problems(metrics, cfg, task)` as a `RunWarning`."""
    for message in problems(metrics, cfg, task):
        warnings.warn(message, RunWarning, stacklevel=3)
