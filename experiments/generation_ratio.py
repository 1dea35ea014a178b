"""Time of one jitted generation of several configs, as ratios to QD's, measured in turns.

    python experiments/generation_ratio.py [--task obstacle2d] [--configs mqd mqd:ensemble_size=4 ...]

Each config ("NAME" or "NAME:OPTION=VALUE,OPTION=VALUE", options of the preset; NAME a
preset or a composition of `sample_efficiency.py`)
grows a repertoire for `--grow` generations (Table II's settings for the task,
`Config.paper`: the robotic column on the KUKA tasks; by default its number of
generations, so the repertoire is as full as at the end of a run), then its
generation is timed from that state: `--rounds` rounds, each taking the median
of `--calls` calls of every config in turn, so that a slow spell of the
machine hits all of them; a config's time is its fastest round's median. QD is
always measured and is the baseline of the ratios.
"""

from __future__ import annotations

import argparse

import jax
import report
from sample_efficiency import configured

from mqd_jax import Config, init
from mqd_jax.core.run import generation, run_generations


def ms_per_generation(task: str, specs: list[str], generations: int | None = None, rounds: int = 5,
                      calls: int = 20) -> dict[str, float]:
    """{spec: ms} of one jitted generation of each config on `task` (QD's first, as "qd"), each grown for
    `generations` generations (default: the task's Table II number) and timed in turns (see the module's doc)."""
    grow = jax.jit(run_generations, static_argnums=(1, 3))
    timed = {}
    generations = Config.paper(task).max_generations if generations is None else generations
    for spec in dict.fromkeys(["qd", *specs]):
        cfg = configured(spec, task)
        params = cfg.params()
        state, _ = grow(init(jax.random.PRNGKey(0), cfg), cfg, params, generations)
        step = jax.jit(lambda s, cfg=cfg, params=params: generation(s, cfg, params))
        timed[spec] = (step, state, [])
    for _ in range(rounds):
        for step, state, times in timed.values():
            times.append(report.median_ms(lambda step=step, state=state: step(state), calls))
    return {spec: min(times) for spec, (_, _, times) in timed.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="obstacle2d")
    parser.add_argument("--configs", nargs="+", default=["mqd", "mqd-paper"])
    parser.add_argument("--grow", type=int, default=None, help="default: the task's Table II generations")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--calls", type=int, default=20)
    args = parser.parse_args()
    generations = Config.paper(args.task).max_generations if args.grow is None else args.grow
    ms = ms_per_generation(args.task, args.configs, generations, args.rounds, args.calls)
    print(f"{args.task}, Table II's settings, after {generations} generations; {report.machine()}; fastest of "
          f"{args.rounds} rounds' medians of {args.calls} calls.\n")
    print("| config | ms per generation | x QD |\n|---|---|---|")
    for spec, value in ms.items():
        print(f"| {spec} | {value:.2f} | {value / ms['qd']:.2f} |")


if __name__ == "__main__":
    main()
