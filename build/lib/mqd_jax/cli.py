"""The `mqd` command line: `mqd run` runs one search with a progress line per chunk."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
import warnings

import jax
import numpy as np

from mqd_jax import checkpoint
from mqd_jax.config import Config
from mqd_jax.run import State

PRESETS = {"paper-2d": Config.paper_2d, "paper-robot": Config.paper_robot}
# Short flags kept from the first versions of the CLI.
_ALIASES = {"max_generations": ["--generations"], "population_size": ["--population"]}


def _add_config_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per Config field (`--t-nov 0.05`, `--budgeted/--no-budgeted`); unset flags keep the preset's value."""
    parser.add_argument("--preset", choices=sorted(PRESETS), default="paper-2d")
    for field in dataclasses.fields(Config):
        flags = ["--" + field.name.replace("_", "-"), *_ALIASES.get(field.name, [])]
        if isinstance(field.default, bool):
            parser.add_argument(*flags, dest=field.name, action=argparse.BooleanOptionalAction, default=None)
        else:
            parser.add_argument(*flags, dest=field.name, type=type(field.default), default=None,
                                help=f"Config.{field.name} (default: the preset's, {field.default!r} in Config)")


def _config(args: argparse.Namespace) -> Config:
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(Config) if getattr(args, f.name) is not None}
    # The main job is a short run: 100 generations unless told otherwise.
    return PRESETS[args.preset](**{"max_generations": 100, **given})


def _run(args: argparse.Namespace) -> None:
    cfg = _config(args)
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "checkpoint.msgpack")
    if os.path.exists(path) and not args.resume:
        print(f"starting afresh; pass --resume to continue the checkpoint in {path}")
    start = time.perf_counter()
    totals = {"discarded": 0, "generations": 0}  # over the chunks this process ran

    def progress(state: State, m: dict[str, np.ndarray]) -> None:
        totals["discarded"] += int(m["discarded"].sum())
        totals["generations"] += len(m["coverage"])
        print(f"generation {int(state.generation):4d}  coverage {m['coverage'][-1]:.3f}  "
              f"size {int(m['repertoire_size'][-1]):5d}  evaluations {int(m['num_evaluations'][-1]):7d}  "
              f"discarded {totals['discarded']:6d}  {totals['generations'] / (time.perf_counter() - start):.1f} gen/s",
              flush=True)

    state, metrics = checkpoint.run_with_checkpoints(
        jax.random.PRNGKey(args.seed), cfg, path, every=max(1, args.chunk), resume=args.resume, on_chunk=progress)
    dropped = int(metrics["dropped_full"].sum())
    if dropped:
        warnings.warn(f"{dropped} new niches did not fit: raise --capacity above {cfg.capacity}", stacklevel=1)
    print(f"done: coverage {metrics['coverage'][-1]:.3f}, mean quality {metrics['mean_quality'][-1]:.3f}, "
          f"{int(state.repertoire.count)} skills, {int(metrics['num_evaluations'][-1])} evaluations, "
          f"{time.perf_counter() - start:.1f} s (compilation included)")
    with open(os.path.join(args.out, "metrics.json"), "w") as f:
        # NaN (a metric that does not apply) becomes null: strict JSON.
        json.dump({k: [None if x != x else x for x in v.tolist()] for k, v in metrics.items()}, f)
    n = int(state.repertoire.count)
    np.savez(os.path.join(args.out, "repertoire.npz"), actions=np.asarray(state.repertoire.actions[:n]),
             behaviors=np.asarray(state.repertoire.behaviors[:n]), qualities=np.asarray(state.repertoire.qualities[:n]))
    _plot(metrics, np.asarray(state.repertoire.behaviors[:n]), os.path.join(args.out, "run.png"))


def _plot(metrics: dict[str, np.ndarray], behaviors: np.ndarray, path: str) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed (pip install -e .[plot]): no plot written")
        return
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 4))
    ax1.plot(metrics["num_evaluations"], metrics["coverage"])
    ax1.set(xlabel="evaluations", ylabel="coverage")
    ax2.scatter(behaviors[:, 0], behaviors[:, 1], s=2)
    ax2.set(xlabel="behavior x", ylabel="behavior y", aspect="equal")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    print(f"wrote {path}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="mqd", description="Model-Based Quality-Diversity search in JAX")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run one search and write metrics, repertoire and a plot")
    _add_config_flags(run)
    run.add_argument("--seed", type=int, default=0)
    run.add_argument("--chunk", type=int, default=25,
                     help="generations per compiled chunk: one progress line and one checkpoint each")
    run.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.msgpack")
    run.add_argument("--out", default="results/run")
    args = parser.parse_args(argv)
    try:
        _run(args)
    except ValueError as e:  # invalid configuration: say what, not a traceback
        parser.error(str(e))


if __name__ == "__main__":
    main()
