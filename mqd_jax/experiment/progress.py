"""Progress of a run, a sweep or an adaptation: a hook the Python runners call (`Progress`, which does nothing),
the command line's bar (`Bar`: tqdm, with the rate and the time left) where its output is a terminal, and its
lines (`Lines`) where it is not; `Steps`, the same for steps that are not generations (`mqd adapt`).

The runners (`checkpoint.run_with_checkpoints`, `sweep.run_batch`, `run` below) take `progress=`: they call
`resume(done, metrics)` where they start, `compiling()` and `compiled()` around the compilation, `chunk(done,
metrics)` after each chunk of generations and `close()` at the end. `run(key, cfg, progress=Bar("", G))` is
`run_mqd` with a bar, its result the same bit for bit.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import sys
import time
from typing import Any

import jax
import numpy as np

from mqd_jax.core.config import Config, check_params
from mqd_jax.core.state import init
from mqd_jax.experiment import files
from mqd_jax.experiment.checkpoint import run_chunks


class Progress:
    """The neutral hook: every event does nothing. `done`: the generations done so far."""

    done = 0

    def resume(self, done: int, metrics: dict[str, np.ndarray]) -> None:
        self.done = done

    def compiling(self, cache: str = "", last: float | None = None) -> None:
        """The program is being compiled (`cache`: what the persistent cache does; `last`: the seconds the last
        compile of this config took, where known)."""

    def compiled(self) -> None:
        """It is compiled (or loaded)."""

    def chunk(self, done: int, metrics: dict[str, np.ndarray]) -> None:
        """`done` generations are done; metrics: the chunk's, [chunk] (a run) or [runs, chunk] (a batch)."""
        self.done = done

    def close(self) -> None:
        """The run ended."""


# Programs compiled or loaded (XLA's compile step, JAX's monitoring events) and the persistent cache's hits since
# the process started: a start whose every program was a hit loaded them instead of compiling.
_PROGRAMS, _CACHE_HIT = "/jax/core/compile/backend_compile_duration", "/jax/compilation_cache/cache_hits"
_CACHE_EVENTS = dict.fromkeys((_PROGRAMS, _CACHE_HIT), 0)


def _count_cache_event(event: str, *_: Any, **__: Any) -> None:
    if event in _CACHE_EVENTS:
        _CACHE_EVENTS[event] += 1


jax.monitoring.register_event_listener(_count_cache_event)
jax.monitoring.register_event_duration_secs_listener(_count_cache_event)


class Lines(Progress):
    """Progress lines for chunks of metrics [generations] (one run) or [runs, generations] (a sweep): what the
    command line prints where its output is not a terminal (a log file).

    Generations per second count from the end of compilation; `discarded`
    (shown for emitters that report it) continues from the resumed metrics.
    """

    def __init__(self, label: str, total: int, cfg: Config | None = None, folder: str | None = None,
                 cache_note: str = "") -> None:
        self.label, self.total = label, total
        # Where a compile's time is remembered (the compilation cache's folder) and for which config; what the
        # compile line says of the cache.
        self.cfg, self.folder, self.cache_note = cfg, folder, cache_note
        self.done, self.discarded, self.since, self.start = 0, 0, 0, time.perf_counter()

    def resume(self, done: int, metrics: dict[str, np.ndarray]) -> None:
        self.done = self.since = done
        if "discarded" in metrics:
            self.discarded = int(np.atleast_2d(metrics["discarded"]).sum(1).mean())

    def compiling(self, cache: str = "", last: float | None = None) -> None:
        last = last if last is not None or self.cfg is None else last_compile(self.folder, self.cfg)
        before = "" if last is None else f"; the last compile of this config here took {last:.1f} s"
        print(f"{self.label}preparing the program (compiled once per config and machine; {cache or self.cache_note}"
              f"{before}) ...", flush=True)
        self.start, self.cache = time.perf_counter(), dict(_CACHE_EVENTS)

    def compiled(self) -> None:
        programs, hits = (_CACHE_EVENTS[e] - self.cache[e] for e in (_PROGRAMS, _CACHE_HIT))
        done = ("compiled" if hits < programs else "loaded the compiled program from the cache" if programs
                else "the program was ready (compiled earlier in this process)")
        self.seconds, self.fresh = time.perf_counter() - self.start, hits < programs
        print(f"{self.label}{done} in {self.seconds:.1f} s", flush=True)
        if self.fresh and self.cfg is not None:
            remember_compile(self.folder, self.cfg, self.seconds)
        self.start, self.since = time.perf_counter(), self.done

    def chunk(self, done: int, m: dict[str, np.ndarray]) -> None:
        self.done = done
        print(f"{self.label}generation {done:4d}/{self.total}  {self.summary(m)}", flush=True)

    def summary(self, m: dict[str, np.ndarray]) -> str:
        """The chunk's coverage (+- across runs), repertoire size, rollouts, discarded and rate."""
        done = self.done
        cov = np.atleast_2d(m["coverage"])[:, -1]
        spread = f" +- {cov.std():.3f}" if len(cov) > 1 else ""
        discarded = ""
        if "discarded" in m:
            self.discarded += int(np.atleast_2d(m["discarded"]).sum(1).mean())  # per run
            discarded = f"  discarded {self.discarded:6d}"
        mean = lambda name: np.atleast_2d(m[name])[:, -1].mean()  # noqa: E731
        rate = (done - self.since) / max(time.perf_counter() - self.start, 1e-9)
        return (f"coverage {cov.mean():.3f}{spread}  size {mean('repertoire_size'):6.0f}  evaluations "
                f"{mean('num_evaluations'):7.0f}{discarded}  {rate:.1f} gen/s")


class Bar(Lines):
    """A progress bar (tqdm: generations done, their rate and the time left, the latest coverage), the lines of
    compilation as `Lines` prints them."""

    def __init__(self, label: str, total: int, cfg: Config | None = None, folder: str | None = None,
                 cache_note: str = "") -> None:
        from tqdm.auto import tqdm

        super().__init__(label, total, cfg, folder, cache_note)
        self.bar = tqdm(total=total, desc=label.rstrip(": ") or "run", unit="gen", dynamic_ncols=True, leave=True)

    def resume(self, done: int, metrics: dict[str, np.ndarray]) -> None:
        super().resume(done, metrics)
        self.bar.n = done
        self.bar.refresh()

    def chunk(self, done: int, m: dict[str, np.ndarray]) -> None:
        step, self.done = done - self.done, done
        self.bar.set_postfix_str(self.summary(m).split("  ")[0], refresh=False)  # the coverage
        self.bar.update(step)

    def close(self) -> None:
        self.bar.close()


def for_output(label: str, total: int, cfg: Config | None = None, folder: str | None = None,
               cache_note: str = "") -> Lines:
    """`Bar` where standard output is a terminal and tqdm is installed (the `plot` extra), else `Lines`; either
    remembers how long `cfg`'s compile took in `folder` (the compilation cache's) and says it the next time, and
    says `cache_note` of the cache."""
    if _terminal_tqdm() is not None:
        return Bar(label, total, cfg, folder, cache_note)
    return Lines(label, total, cfg, folder, cache_note)


def _terminal_tqdm() -> Any:
    """tqdm's bar class where standard output is a terminal and tqdm is installed (the `plot` extra), else None."""
    if not sys.stdout.isatty():
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    return tqdm


class Steps:
    """Progress over `total` steps of work that is not generations (`mqd adapt`: one step per task and method):
    a tqdm bar with the rate and the time left where standard output is a terminal and tqdm is installed; each
    step's line is printed either way (above the bar, which stays at the bottom)."""

    def __init__(self, label: str, total: int, unit: str) -> None:
        tqdm = _terminal_tqdm()
        self.bar = None if tqdm is None else tqdm(total=total, desc=label, unit=unit, dynamic_ncols=True, leave=True)

    def step(self, line: str, now: str = "") -> None:
        """One step done: its `line` printed; `now`, the step just done, beside the bar."""
        if self.bar is None:
            print(line, flush=True)
            return
        self.bar.write(line)
        self.bar.set_postfix_str(now, refresh=False)
        self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# The compile times the command line remembers, per config, in the compilation cache's folder.
COMPILE_TIMES = "compile_times.json"
MAX_TIMES = 2**20  # the largest record of compile times read (bytes): a line per config


def _config_key(cfg: Config) -> str:
    return hashlib.sha256(json.dumps(cfg.to_dict(), sort_keys=True, default=repr).encode()).hexdigest()[:16]


def last_compile(folder: str | None, cfg: Config) -> float | None:
    """The seconds the last compile of `cfg`'s program took, as `remember_compile` wrote them in `folder` (the
    compilation cache's), or None."""
    if folder is None:
        return None
    try:
        value = json.loads(files.read_bytes(os.path.join(folder, COMPILE_TIMES), MAX_TIMES)).get(_config_key(cfg))
    except (OSError, ValueError, AttributeError, RecursionError):
        return None
    return float(value) if isinstance(value, int | float) else None


def remember_compile(folder: str | None, cfg: Config, seconds: float) -> None:
    """Writes the seconds a compile of `cfg`'s program took into `folder`'s `COMPILE_TIMES` (nothing without a
    folder; a file that cannot be read or written is started afresh or left)."""
    if folder is None:
        return
    path = os.path.join(folder, COMPILE_TIMES)
    try:
        times = json.loads(files.read_bytes(path, MAX_TIMES))
        times = times if isinstance(times, dict) else {}
    except (OSError, ValueError, RecursionError):
        times = {}
    times[_config_key(cfg)] = round(seconds, 2)
    with contextlib.suppress(OSError, ValueError):  # never through a link, nor into anything but a regular file
        files.write(path, json.dumps(times).encode())


def run(key: jax.Array, cfg: Config, params: Any = None, chunk: int | None = None,
        progress: Progress | None = None) -> tuple[Any, dict[str, np.ndarray]]:
    """`run_mqd(key, cfg, params)` in chunks of `chunk` generations (default: a twentieth of the run), calling
    `progress` (`Bar("", cfg.max_generations)` for a bar) as it goes; the same result bit for bit (one compiled
    chunk, as `checkpoint.run_with_checkpoints` runs, without its file). Metrics as numpy arrays [generations]."""
    progress = progress or Progress()
    params = cfg.params() if params is None else params
    check_params(params, cfg)
    state = init(key, cfg)
    progress.resume(0, {})
    return run_chunks(state, {}, cfg, params, chunk or max(1, cfg.max_generations // 20), progress)
