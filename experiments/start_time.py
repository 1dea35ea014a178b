"""First and second start of the README's main command (`mqd run --generations 100`), with a fresh cache.

Runs the command `--repeats` times in a row as separate processes, all sharing one new,
empty compilation cache (so the first start compiles and the later ones load), plus one
start with `--no-cache` for reference. For each it reports the wall time from launching the
process until the first generation starts (the "compiled in" line is printed just before),
the time the command reports for compiling, and the whole wall time. Also times the
import of the command line alone, the part of a start that no cache can remove.

    python experiments/start_time.py [--repeats 3] [--out results/start_time]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time

import report

COMMAND = ["mqd", "run", "--generations", "100"]


def start(argv: list[str], env: dict[str, str]) -> dict[str, float]:
    """Launches `argv`, reading its output as it comes; the times (s) of its milestones."""
    began = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    found: dict[str, float] = {}
    for line in proc.stdout:
        if line.startswith(("compiled in", "loaded the compiled program from the cache in")):
            found["to first generation"] = time.perf_counter() - began
            found["compiling (reported)"] = float(re.findall(r"[\d.]+", line)[0])
    if proc.wait() != 0:
        raise SystemExit(f"{' '.join(argv)} failed")
    found["whole command"] = time.perf_counter() - began
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3, help="starts with the cache (the first one compiles)")
    parser.add_argument("--out", default="results/start_time")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as work:
        env = {**os.environ, "MQD_JAX_CACHE_DIR": cache}
        out = ["--overwrite", "--out", os.path.join(work, "run")]
        rows = [("no cache", start([*COMMAND, *out, "--no-cache"], env))]
        rows += [(f"start {i + 1} ({'empty' if i == 0 else 'warm'} cache)", start([*COMMAND, *out], env))
                 for i in range(args.repeats)]
        began = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import mqd_jax.experiment.cli"], check=True)
        imports = time.perf_counter() - began
    columns = ["to first generation", "compiling (reported)", "whole command"]
    first = rows[1][1]["to first generation"]
    lines = [f"`{' '.join(COMMAND)}` (2D Obstacle, QD, population 100); {report.machine()}.", "",
             "| start | " + " | ".join(f"{c} (s)" for c in columns) + " | to first generation / first start |",
             "|---" * (len(columns) + 2) + "|"]
    lines += [f"| {name} | " + " | ".join(f"{r[c]:.1f}" for c in columns) +
              f" | {r['to first generation'] / first:.2f} |" for name, r in rows]
    lines += ["", f"Importing the command line alone (a new Python process): {imports:.1f} s."]
    report.write(lines, os.path.join(args.out, "start_time.md"))


if __name__ == "__main__":
    main()
