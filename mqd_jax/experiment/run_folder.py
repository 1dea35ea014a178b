"""A `mqd run` results folder and every decision about it: what it holds, what a run may do to it (start, resume,
start afresh over it), each refusal with its message, and the files a finished run leaves. The command
(`run_command`) parses the flags and prints; nothing here compiles, so each decision is testable on its own.

The folder belongs to one run (config and seed, `folders.claim`); another is refused unless `--overwrite`; a
checkpoint of this run is refused without `--resume` (naming the generations `--overwrite` would delete); a
finished run is refused unless `--overwrite`; a damaged file is set aside, never deleted.
"""

from __future__ import annotations

import dataclasses
import json
import os
from typing import Any

import jax
import numpy as np

from mqd_jax.core.config import Config
from mqd_jax.core.state import State, get_task
from mqd_jax.experiment import checkpoint, files, folders, manifest, messages, migrations, plots, results, tables
from mqd_jax.experiment.provenance import provenance

RUN_FILES = ("metrics.json", "repertoire.npz", "run.png", "checkpoint.msgpack")


def upgraded_identity(identity: dict[str, Any]) -> dict[str, Any]:
    """A run folder's identity saved by an earlier version, its config in today's form."""
    if not isinstance(identity.get("config"), dict):
        return identity
    return {**identity, "config": migrations.upgraded(identity["config"])}


def check_file(path: str) -> None:
    """Raises ValueError if the results file `path` is damaged (what `--overwrite` sets aside rather than deletes):
    a checkpoint that `checkpoint.read` refuses, a JSON or npz file that fails its checksum."""
    if path.endswith(".msgpack"):
        checkpoint.read(path)
    elif path.endswith(".json"):
        files.read_json(path, "")
    elif path.endswith(".npz"):
        files.read_npz(path, "")


@dataclasses.dataclass(frozen=True)
class RunFolder:
    """The results folder `out` of `mqd run`. Its methods that change the folder are called holding its lock
    (`folders.lock(out)`); each refusal is a ValueError whose message says what to do."""

    out: str

    @property
    def checkpoint(self) -> str:
        return os.path.join(self.out, "checkpoint.msgpack")

    def resume_command(self) -> str:
        """The command that continues the run saved here, as it runs when pasted."""
        return messages.command("mqd", "run", "--resume", ("--out", self.out))

    def progress(self) -> tuple[int, int] | None:
        """(generations done, of how many) of the checkpoint here; None where there is none or it is damaged."""
        if not files.is_file(self.checkpoint):
            return None
        try:
            payload = checkpoint.read(self.checkpoint)
            return int(np.asarray(payload["state"]["generation"]).reshape(-1)[0]), \
                int(payload["config"]["max_generations"])
        except (ValueError, KeyError, TypeError, IndexError):
            return None

    def interrupted(self, done: int) -> str:
        """What Ctrl-C says after `done` generations were saved here (0: none)."""
        if done:
            return f"interrupted at generation {done}; `{self.resume_command()}` continues from there"
        kept = os.path.lexists(self.checkpoint)
        return ("interrupted before a generation was saved; " +
                (f"the checkpoint already in {self.out!r} is kept as it was" if kept else "nothing was saved"))

    @staticmethod
    def check_request(resume: bool, overwrite: bool) -> None:
        """Refuses `--resume` with `--overwrite`."""
        if resume and overwrite:
            raise ValueError("--resume and --overwrite together: --resume continues the run in the folder, "
                             "--overwrite starts it afresh; give one")

    def check_resumable(self) -> None:
        """Refuses `--resume` where there is no checkpoint."""
        if not files.lexists(self.checkpoint):
            raise ValueError(f"--resume: {self.out!r} holds no checkpoint; run without --resume to start")

    def claim(self, cfg: Config, seed: int, resume: bool, overwrite: bool,
              saved: tuple[int, int] | None) -> list[tuple[list[str], str]]:
        """Makes the folder this run's (`folders.claim`), refusing another run's results unless `overwrite`, and a
        checkpoint of this run without `resume` (unless `overwrite`, which deletes it, or sets it aside if
        damaged); `saved`: the checkpoint's `progress()`, read once by the caller. Returns what was removed or set
        aside, each with why, for the command to say."""
        stake = f"; its checkpoint holds {saved[0]} of {saved[1]} generations" if saved else ""
        said = [(folders.claim(self.out, "run", {"config": cfg.to_dict(), "seed": seed}, RUN_FILES, overwrite,
                               upgrade=upgraded_identity, check=check_file, at_stake=stake), "--overwrite")]
        if files.is_file(self.checkpoint) and not resume:
            if not overwrite and saved and saved[0] >= cfg.max_generations:
                raise ValueError(f"{self.out!r} holds this run, finished ({cfg.max_generations} generations): its "
                                 "results are there; --overwrite runs it again (deleting them)")
            if not overwrite:
                what = f"at generation {saved[0]} of {saved[1]}" if saved else "that is damaged"
                fate = f"deleting those {saved[0]} generations" if saved else "setting the damaged one aside"
                raise ValueError(f"{self.out!r} holds a checkpoint of this run {what}: `{self.resume_command()}` "
                                 f"continues it; --overwrite starts afresh, {fate}")
            ours = [n for n in manifest.written(self.out) if n in RUN_FILES]
            said.append((folders.discard(self.out, ours, check_file), "--overwrite (starting afresh)"))
        return said

    def cannot_continue(self, refused: checkpoint.Refused, saved: tuple[int, int] | None) -> ValueError:
        """The refusal of a checkpoint the run cannot continue from (`saved`: its progress, read before the run),
        with what starting afresh does to it."""
        fresh = "The run's own command with --overwrite (in place of --resume)"
        try:
            check_file(self.checkpoint)
            fate = f"deletes it ({saved[0]} of {saved[1]} generations)" if saved else "deletes it"
        except ValueError:
            fate = "sets it aside as checkpoint.msgpack.damaged (never deletes it)"
        return ValueError(f"{refused}; the run cannot continue from it. {fresh} starts it afresh and {fate}")

    def write(self, cfg: Config, seed: int, key: jax.Array, state: State,
              metrics: dict[str, np.ndarray]) -> tuple[dict[str, Any], list[str]]:
        """Writes the finished run's metrics.json, repertoire.npz and run.png (where the plot extra is installed);
        returns their shared description (config, seed, key, coverage measure, implementation, provenance) and
        the paths written, the manifest last."""
        meta = {"config": cfg.to_dict(), "seed": seed, "key": np.asarray(key).tolist(),
                "coverage_measured": tables.coverage_measure(cfg, metrics["coverage"][-1]),
                "implementation": results.implementation(cfg), "provenance": provenance()}
        folders.write_json(os.path.join(self.out, "metrics.json"), {**meta, "metrics": metrics})
        n = int(state.repertoire.count)
        rep = jax.device_get(state.repertoire)
        description = json.dumps(meta)
        folders.write_npz(os.path.join(self.out, "repertoire.npz"), actions=rep.actions[:n],
                          behaviors=rep.behaviors[:n], qualities=rep.qualities[:n], meta=np.asarray(description))
        title = f"{cfg.task}, {cfg.algorithm}, seed {seed}, {cfg.max_generations} generations"
        figure = plots.run_figure(get_task(cfg), metrics, rep.behaviors[:n], os.path.join(self.out, "run.png"),
                                  title, description, rep.qualities[:n])
        written = [f for f in RUN_FILES if f != "run.png" or figure]
        return meta, [os.path.join(self.out, f) for f in [*written, manifest.MANIFEST]]
