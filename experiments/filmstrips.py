"""A filmstrip (frames side by side, one PNG) of one skill per robot task, rendered offscreen by MuJoCo.

    MUJOCO_GL=egl python experiments/filmstrips.py [--tasks ...] [--frames 6] [--out docs/figures]

The skills are written out below (a push along +x that moves the cube, a push of the ball across the table, a
place on the high shelf, the hexapod's tripod gait turning left: its right legs' hips offset forward), so the
strips need no run; `mqd render DIR` animates any skill of a run.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
from PIL import Image

from mqd_jax.core import registry

SKILLS = {
    "push_cube": [0.45, 0.0, 0.0, 60, 0.8, 0.0, 0.0, 100],
    "push_sphere": [0.5, -0.03, 0.0, 40, 0.75, 0.03, 0.0, 60],
    "place": [0.6, 0.0, 0.3, 0.0, 60] * 2 + [0.7, -0.2, 0.3, 0.5, 60] * 2 + [0.75, -0.3, 0.22, 0.5, 60],
    "hexapod_omni": [1.0, 0.0, 1.0, 0.0, 1.0, 1.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0,  # left legs: the tripod gait
                     1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0],  # right: hips offset forward
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(SKILLS), choices=list(SKILLS))
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--out", default="docs/figures")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    for name in args.tasks:
        action = SKILLS[name]
        task = registry.make(name, backend="mujoco")
        _, _, valid = task.evaluate(np.asarray([action], np.float32), None)
        # Render only the frames shown: one every `every` steps, the last at most a step before the end.
        every = max(1, (task.horizon - 1) // (args.frames - 1))
        picks = task.frames(np.asarray(action, np.float32), 320, 240, every=every)[:args.frames]
        path = os.path.join(args.out, f"filmstrip_{name}.png")
        Image.fromarray(np.concatenate(list(picks), axis=1)).save(path)
        print(f"{path}: {len(picks)} frames, one every {every} of {task.horizon} steps "
              f"(valid: {bool(np.asarray(valid)[0])})")


if __name__ == "__main__":
    main()
