"""The tables of a sweep folder, as markdown: Table I (coverage, QD-score, quality per task and algorithm, with
the Mann-Whitney test between M-QD and QD), the adaptation table, and how a run's coverage was measured."""

from __future__ import annotations

import json
import os
from collections.abc import Callable

import numpy as np

from mqd_jax.core import algorithms, coverage
from mqd_jax.core.config import Config
from mqd_jax.core.state import coverage_method, coverage_points, get_task
from mqd_jax.experiment import files, manifest
from mqd_jax.experiment.folders import write_atomically
from mqd_jax.experiment.provenance import provenance
from mqd_jax.experiment.results import Runs, task_order
from mqd_jax.experiment.stats import mann_whitney

NAMES = {"mqd": "M-QD", "mqd-paper": "M-QD (paper's filter)", "qd": "QD", "random": "RANDOM",
         "mqd-local": "M-QD (local fits)"}


# The paper's name (`Task.paper_coverage`'s key) of each preset that reproduces one of its algorithms.
PAPER_ALGORITHM = {"mqd-paper": "mqd", "qd": "qd", "random": "random"}


def write_markdown(lines: list[str], path: str, show: bool = True) -> None:
    """Writes a markdown report to `path` atomically (creating its folder unless it is a locked one), and prints
    it if `show`. Its last line is an HTML comment (invisible where markdown is shown) with mqd-jax's provenance
    (`manifest.MARK`): what proves the file mqd-jax's in a folder without a manifest."""
    text = "\n".join(lines)
    if show:
        print(text)
    files.make_folder(os.path.dirname(path) or ".")
    mark = manifest.MARK + json.dumps({"provenance": provenance()}) + " -->"
    write_atomically(path, (text + "\n\n" + mark + "\n").encode())


def coverage_measure(cfg: Config, value: np.ndarray | float | None = None) -> str:
    """How `cfg`'s coverage is measured, in words: "grid of 256^2 cells" (exact up to the cells), or "Monte Carlo,
    N reachable points of M" with the standard error of `value` (the mean of the final coverages given)."""
    if coverage_method(cfg) == coverage.GRID:
        d = get_task(cfg).behavior_dim
        return f"grid of {coverage.axis_cells(d, cfg.coverage_resolution)}^{d} cells"
    reachable = int(np.sum(coverage_points(cfg)[1]))
    text = f"Monte Carlo, {reachable} reachable points of {cfg.coverage_samples}"
    if value is not None:
        text += f", standard error {float(coverage.standard_error(np.mean(value), reachable)):.1e}"
    return text


def normalized_qd_score(cfg: Config, qd_score: np.ndarray) -> np.ndarray:
    """QD-score / ((quality_high - quality_low) x capacity): 1 = every slot of the repertoire filled at the
    task's highest quality (pyribs' `norm_qd_score` divides by the archive's cells; a repertoire's are its
    `capacity` slots)."""
    low, high = get_task(cfg).quality_range
    return np.asarray(qd_score) / ((high - low) * cfg.capacity)


def _pm(x: np.ndarray, digits: int = 3) -> str:
    return f"{np.mean(x):.{digits}f} +- {np.std(x):.{digits}f}"


def _p_value(by: dict[str, Runs], a: str, b: str) -> str:
    """Two-sided Mann-Whitney U p-value of final coverage, algorithm a vs b ('' unless both ran)."""
    if a not in by or b not in by:
        return ""
    return f"{mann_whitney(by[a].final('coverage'), by[b].final('coverage'))[1]:.2g}"


def failed_runs(r: Runs) -> int:
    """How many of the runs `r` had every rollout fail (nothing could be inserted: their coverage and quality are
    those of an empty repertoire, not measurements)."""
    if "invalid" not in r.metrics:
        return 0
    total = r.final("num_evaluations")
    return int(np.sum((total > 0) & (np.nansum(r.metrics["invalid"], axis=1) >= total)))


def table_one(runs: dict[str, dict[str, Runs]], missing: list[tuple[str, str]] = ()) -> list[str]:
    """Markdown: Table I (final coverage, the paper's layout, the paper's values beside our runs of its
    algorithms: "mqd-paper", "qd", "random"), the mean-quality
    table, and per task the evaluations, wall times and two-sided Mann-Whitney U p-values on final coverage.
    Runs whose every rollout failed are marked; `missing` (task, algorithm) batches, planned but not in the folder,
    are named first."""
    algs = [a for a in algorithms.names() if any(a in r for r in runs.values())]
    seeds = sorted({len(r.keys) for by in runs.values() for r in by.values()})

    def cells(task: str, cell: Callable[[str, Runs], str]) -> list[str]:
        return [cell(a, runs[task][a]) if a in runs[task] else "" for a in algs]

    def row(*columns: str) -> str:
        return "| " + " | ".join(columns) + " |"

    def failed(r: Runs) -> str:
        n = failed_runs(r)
        return f" [every rollout failed in {n} of {len(r.keys)} runs]" if n else ""

    def coverage(task: str, a: str, r: Runs) -> str:
        # The paper's value only beside runs of its algorithms made with its settings (Table II).
        paper = (get_task(r.cfg).paper_coverage.get(PAPER_ALGORITHM[a])
                 if a in PAPER_ALGORITHM and r.cfg == Config.paper(task, algorithm=a) else None)
        return _pm(r.final("coverage")) + (f" (paper {paper[0]} +- {paper[1]})" if paper else "") + failed(r)

    head = [row("task", *(NAMES.get(a, a) for a in algs)), "|---" * (len(algs) + 1) + "|"]
    absent = [f"Missing: {', '.join(f'{t} {NAMES.get(a, a)}' for t, a in missing)}: planned by `mqd sweep` in "
              "this folder but not in it (the sweep was interrupted or failed there; the same command runs them)",
              ""] if missing else []
    lines = [*absent, f"Seeds per task: {', '.join(map(str, seeds))}; mean +- std over seeds.", "",
             "Table I: final coverage (the paper's in brackets, shown only beside runs with Table II's settings, "
             "`Config.paper`)", "", *head]
    lines += [row(t, *cells(t, lambda a, r, t=t: coverage(t, a, r))) for t in runs]
    lines += ["", "Final mean quality", "", *head]
    lines += [row(t, *cells(t, lambda a, r: _pm(r.final("mean_quality")) + failed(r))) for t in runs]
    lines += ["", "Standard metrics (pyribs' and QDax's definitions), final, mean +- std over seeds: skills in the "
              "repertoire; QD-score = sum over skills of (quality - the task's lowest quality, `quality_range`); "
              "normalized = QD-score / ((highest - lowest quality) x capacity); max and mean quality; how coverage "
              "is measured (blank: runs saved before version 0.12)", "",
              row("task", "algorithm", "skills", "QD-score", "normalized QD-score", "max quality", "mean quality",
                  "coverage measured"), "|---" * 8 + "|"]
    for t, by in runs.items():
        for a, r in by.items():
            final = lambda name, digits=3, r=r: _pm(r.final(name), digits) if name in r.metrics else ""  # noqa: E731
            normalized = (_pm(normalized_qd_score(r.cfg, r.final("qd_score")), 4) if "qd_score" in r.metrics
                          else "")
            lines.append(row(t, NAMES.get(a, a), final("repertoire_size", 1), final("qd_score", 1), normalized,
                             final("max_quality"), final("mean_quality"),
                             coverage_measure(r.cfg, r.final("coverage"))))
    lines += ["", "Evaluations (rollouts) per run; wall time of each batch of seeds (compilation included); "
              "two-sided Mann-Whitney U p-values on final coverage", "",
              row("task", *(f"{NAMES.get(a, a)} evaluations" for a in algs),
                  *(f"{NAMES.get(a, a)} wall s" for a in algs),
                  "p M-QD vs QD", "p QD vs RANDOM"), "|---" * (2 * len(algs) + 3) + "|"]
    lines += [row(t, *cells(t, lambda a, r: f"{r.final('num_evaluations').mean():.0f}"),
                  *cells(t, lambda a, r: f"{r.wall_s:.0f}"), _p_value(by, "mqd", "qd"), _p_value(by, "qd", "random"))
              for t, by in runs.items()]
    machines = sorted({r.machine for by in runs.values() for r in by.values()})
    return [*lines, "", "Machine: " + "; ".join(machines)]


def adaptation_table(results: dict[str, dict[str, dict[str, list[float]]]]) -> list[str]:
    """Markdown: per task and method, mean +- std over repertoires of the mean error, mean steps and the
    fraction of goals within t_dist."""
    lines = ["Adaptation of final M-QD repertoires toward reachable goals; mean +- std over repertoires.", "",
             "| task | repertoires x goals | method | mean error | mean steps (= rollouts) | goals within t_dist |",
             "|---|---|---|---|---|---|"]
    for task in sorted(results, key=task_order):
        for method, r in results[task].items():
            lines.append(f"| {task} | {len(r['error'])} x {r['goals']} | {method} | {_pm(r['error'], 4)} | "
                         f"{np.mean(r['steps']):.2f} | {np.mean(r['reached']):.3f} |")
    return lines

