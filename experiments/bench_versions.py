"""ms per generation of QD and M-QD for two source trees of mqd-jax, alternating, on one machine.

    python experiments/bench_versions.py BEFORE_TREE AFTER_TREE [--rounds 5] [--generations 250] [--algorithms qd mqd]

Each round runs, for each tree and algorithm, a fresh process (PYTHONPATH=tree)
that compiles `run_mqd` on 2D Obstacle with the paper's 2D settings, then times
3 runs and reports the median. Rounds alternate the trees so that the machine's
drift hits both alike; the report gives the median over rounds and the
after/before ratio. Compare a tree with a checkout of another commit, e.g.
`git worktree add /tmp/before <rev>`.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys

import report

# Runs in the tree under test (PYTHONPATH), with this folder's timing function.
_TIMING = """
import sys
sys.path.insert(0, {experiments!r})
from accelerator_timings import ms_per_generation
from mqd_jax import Config
print(ms_per_generation(Config.paper_2d(task="obstacle2d", algorithm="{algorithm}", max_generations={generations})))
"""


def _ms_per_generation(tree: str, algorithm: str, generations: int) -> float:
    env = {**os.environ, "PYTHONPATH": os.path.abspath(tree), "MQD_JAX_CACHE_DIR": "off"}
    code = _TIMING.format(experiments=os.path.dirname(os.path.abspath(__file__)), algorithm=algorithm,
                          generations=generations)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return float(out.stdout.split()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before")
    parser.add_argument("after")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--generations", type=int, default=250)
    parser.add_argument("--algorithms", nargs="+", default=["qd", "mqd"])
    args = parser.parse_args()
    times: dict[tuple[str, str], list[float]] = {}
    for r in range(args.rounds):
        for algorithm in args.algorithms:
            for name, tree in (("before", args.before), ("after", args.after))[:: 1 if r % 2 == 0 else -1]:
                ms = _ms_per_generation(tree, algorithm, args.generations)
                times.setdefault((algorithm, name), []).append(ms)
                print(f"round {r + 1}: {algorithm} {name} {ms:.3f} ms/generation", flush=True)
    lines = [f"2D Obstacle, paper 2D settings, {args.generations} generations; median of 3 runs per process, "
             f"median over {args.rounds} alternating rounds; {report.machine()}", "",
             "| algorithm | before ms/gen | after ms/gen | after / before | per-round after / before: median "
             "(range) |", "|---|---|---|---|---|"]
    for algorithm in args.algorithms:
        before, after = (times[(algorithm, n)] for n in ("before", "after"))
        ratios = [a / b for a, b in zip(after, before, strict=True)]
        lines.append(f"| {algorithm} | {statistics.median(before):.3f} | {statistics.median(after):.3f} | "
                     f"{statistics.median(after) / statistics.median(before):.3f} | {statistics.median(ratios):.3f} "
                     f"({min(ratios):.3f}-{max(ratios):.3f}) |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
