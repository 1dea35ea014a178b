"""Coverage against exact values in 1, 2, 3 and 5 dimensions: the grid, the Monte Carlo estimate and its error bar.

    python experiments/coverage_checks.py [--sets 200] [--out docs/data/coverage_checks.md]

Ball configurations whose covered volume is known exactly: intervals in 1-D (their merged length), two
overlapping disks and a third in 2-D (the lens area), two overlapping spheres and a third in 3-D (the lens
volume), 32 disjoint 5-D balls (32 ball volumes), all inside the unit box. For each, what
`mqd_jax.core.coverage` measures by the method a run of the default settings would use
(`coverage.method`), and by the other where it fits; for Monte Carlo its stated standard error. Then, in 5-D,
`--sets` independent sets of points: the share of estimates within one and two stated standard errors of the
exact value (a normal error bar: 68% and 95%).
"""

from __future__ import annotations

import argparse
import math

import jax.numpy as jnp
import numpy as np
import report

from mqd_jax.core import coverage

SAMPLES = 65536


def ball(d: int, r: float) -> float:
    """The volume of a d-ball of radius r."""
    return math.pi ** (d / 2) / math.gamma(d / 2 + 1) * r**d


def lens(d: int, r: float, gap: float) -> float:
    """The overlap of two d-balls of radius r whose centres are `gap` apart (d = 2, 3)."""
    if d == 2:
        return 2 * r**2 * math.acos(gap / (2 * r)) - gap / 2 * math.sqrt(4 * r**2 - gap**2)
    return math.pi * (4 * r + gap) * (2 * r - gap) ** 2 / 12


def cases() -> list[tuple[str, np.ndarray, float, float]]:
    """(name, centres [P, d], radius, exact covered share of the unit box)."""
    rng = np.random.default_rng(3)
    intervals, r1 = rng.random((12, 1)), 0.03
    spans = sorted((max(c - r1, 0.0), min(c + r1, 1.0)) for c in intervals[:, 0])
    length, (lo, hi) = 0.0, spans[0]
    for a, b in spans[1:]:
        if a > hi:
            length, lo = length + hi - lo, a
        hi = max(hi, b)
    out = [("1-D: 12 random intervals, r 0.03", intervals, r1, length + hi - lo)]
    for d, r, gap in ((2, 0.15, 0.1), (3, 0.12, 0.15)):
        centres = np.full((3, d), 0.3)
        centres[1, 0] += gap
        centres[2] = 0.7
        out.append((f"{d}-D: two balls {gap} apart and a third, r {r}", centres, r, 3 * ball(d, r) - lens(d, r, gap)))
    corners = np.stack(np.meshgrid(*[[0.25, 0.75]] * 5, indexing="ij"), -1).reshape(-1, 5)
    out.append(("5-D: 32 disjoint balls, r 0.2", corners, 0.2, len(corners) * ball(5, 0.2)))
    return out


def measure(points: np.ndarray | None, resolution: int, centres: np.ndarray, r: float) -> float:
    """The covered share by Monte Carlo at `points`, or (None) on a grid of `resolution` cells per axis."""
    d = centres.shape[1]
    if points is None:
        cells = coverage.axis_cells(d, resolution)
        cover = coverage.empty(np.zeros(d), np.ones(d), np.ones((cells,) * d, bool), r)
    else:
        cover = coverage.empty_samples(points, np.ones(len(points), bool))
    c = jnp.asarray(centres, jnp.float32)
    return float(coverage.fraction(coverage.stamp(cover, c, jnp.ones(len(c), jnp.int32), jnp.float32(r))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", type=int, default=200)
    parser.add_argument("--out", default="docs/data/coverage_checks.md")
    args = parser.parse_args()
    lines = [f"Command: `python experiments/coverage_checks.py --sets {args.sets}`", "",
             f"Machine: {report.machine()}", "",
             "| case | exact | default method | grid (cells) | grid error | Monte Carlo (65536 points) | "
             "MC error | stated standard error |", "|---|---|---|---|---|---|---|---|"]
    for name, centres, r, exact in cases():
        d = centres.shape[1]
        default = coverage.method(np.zeros(d), np.ones(d), 256, r, 200)
        resolution = 256 if d <= 2 else 128
        fits = d <= 3 and coverage.method(np.zeros(d), np.ones(d), resolution, r, 200) == coverage.GRID
        grid = measure(None, resolution, centres, r) if fits else None
        mc = measure(coverage.sample_points(np.zeros(d), np.ones(d), SAMPLES), 0, centres, r)
        se = float(coverage.standard_error(mc, SAMPLES))
        cells = f"{coverage.axis_cells(d, resolution)}^{d}"
        lines.append(f"| {name} | {exact:.5f} | {default} | "
                     + (f"{grid:.5f} ({cells}) | {grid - exact:+.5f}" if grid is not None else "does not fit | ")
                     + f" | {mc:.5f} | {mc - exact:+.5f} | {se:.5f} |")
    name, centres, r, exact = cases()[-1]
    rng = np.random.default_rng(0)
    z = []
    for _ in range(args.sets):
        value = measure(rng.random((4096, 5)).astype(np.float32), 0, centres, r)
        z.append((value - exact) / float(coverage.standard_error(value, 4096)))
    z = np.asarray(z)
    lines += ["", f"{name}: {args.sets} independent sets of 4096 uniform points; (estimate - exact) / its stated "
              f"standard error: within 1: {np.mean(np.abs(z) <= 1):.2f} (normal: 0.68), within 2: "
              f"{np.mean(np.abs(z) <= 2):.2f} (0.95), within 3: {np.mean(np.abs(z) <= 3):.3f} (0.997); mean "
              f"{z.mean():+.2f}, std {z.std():.2f} (1)."]
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
