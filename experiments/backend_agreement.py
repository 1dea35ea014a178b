"""How closely the MJX or MuJoCo Warp backend agrees with C MuJoCo on a robot task's behaviors, same actions.

    python experiments/backend_agreement.py [--task push_cube] [--backend mjx|warp] [--actions 256]
        [--out results/agreement.md]

Rolls the same random actions (uniform in the task's bounds, fixed seed) out on
C MuJoCo and on `--backend` and reports, over the actions valid on both, the distribution of
the distance between the final object positions, separately for actions that
moved the object (by more than 1 cm on C MuJoCo) and those that did not; the
largest difference in end-effector path length; and how often the two agree on
validity. Slow on a CPU (MJX compiles for minutes, MuJoCo Warp runs on Warp's
CPU device); meant for a GPU machine.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
import report

from envs import kuka
from mqd_jax.core import registry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="push_cube")
    parser.add_argument("--backend", default="mjx", choices=["mjx", "warp"])
    parser.add_argument("--actions", type=int, default=256)
    parser.add_argument("--out", default="results/agreement.md")
    args = parser.parse_args()
    out = {}
    for backend in ("mujoco", args.backend):
        task = registry.make(args.task, backend=backend)
        low, high = jnp.asarray(task.action_low), jnp.asarray(task.action_high)
        actions = jax.random.uniform(jax.random.PRNGKey(0), (args.actions, len(low)), minval=low, maxval=high)
        out[backend] = [np.asarray(x) for x in jax.jit(task.evaluate)(actions, None)]
    (b_c, q_c, v_c), (b_x, q_x, v_x) = out["mujoco"], out[args.backend]
    both = v_c & v_x
    dist = np.linalg.norm(b_c - b_x, axis=1)
    moved = np.linalg.norm(b_c - np.asarray(kuka.TABLE_CENTRE), axis=1) > 0.01
    lines = [f"{args.task}, C MuJoCo vs {args.backend}, {args.actions} random actions, horizon {task.horizon}; "
             f"{report.machine()}.", "",
             f"Same validity on both backends: {np.mean(v_c == v_x):.3f} of actions; valid on both: {both.sum()}.", "",
             "| actions (valid on both) | count | median distance, m | 90th percentile, m | max, m | within 1 cm |",
             "|---|---|---|---|---|---|"]
    for name, sel in (("object not moved", both & ~moved), ("object moved", both & moved)):
        d = dist[sel]
        if len(d):
            lines.append(f"| {name} | {len(d)} | {np.median(d):.4f} | {np.quantile(d, 0.9):.4f} | {d.max():.4f} "
                         f"| {np.mean(d < 0.01):.3f} |")
    lines += ["", f"Quality, largest difference: {np.abs(q_c - q_x)[both].max():.4f}."]
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
