"""A `mqd sweep` results folder and every decision about it: which batches it holds, which conflict with the
planned ones (another config or keys: refused unless `--overwrite`; another implementation: unless
`--rerun-stale`), which are damaged (set aside and run again, or finished from their sound checkpoint), where an
interrupted batch continues, and what Ctrl-C says. The command (`sweep_command`) parses, prints and runs; the
decisions return what is to be said, so each is testable without running a batch.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np

from mqd_jax.core.config import Config
from mqd_jax.core.state import State
from mqd_jax.experiment import checkpoint, files, folders, manifest, results
from mqd_jax.experiment.messages import count_of

Said = list[tuple[list[str], str]]  # files removed or set aside, each list with why (`messages.say_removed`)


@dataclasses.dataclass
class SweepFolder:
    """The results folder `out` of `mqd sweep`, and how many of its batches are finished (`finished`). Its methods
    that change the folder are called holding its lock (`folders.lock(out)`); each refusal is a ValueError whose
    message says what to do."""

    out: str
    finished: int = 0

    def interrupted(self, where: str, done: int = 0, total: int = 0) -> str:
        """What Ctrl-C says `where` the sweep was, `done` of `total` generations into the running batch."""
        text = f"interrupted {where}"
        batches = count_of(self.finished, "finished batch", "finished batches")
        kept = f"the {batches} in {self.out!r} are kept" if self.finished else "no batch had finished"
        if done:
            return (f"{text} at generation {done} of {total}: its checkpoint keeps them, and the same command "
                    f"continues this batch from generation {done}; {kept}")
        return f"{text}; {kept}" + (", and the same command continues from there" if self.finished else "")

    def claim(self, batches: list[tuple[Config, np.ndarray]], overwrite: bool, rerun_stale: bool
              ) -> tuple[list[tuple[str, dict[str, Any]]], Said, list[str]]:
        """Makes the folder a sweep's, and finds every conflict of `batches` with what it holds before anything
        runs (one read of the folder): refuses batches of another config or keys unless `overwrite`, of another
        implementation unless `rerun_stale` (or `overwrite`), and removes those; sets aside the damaged batches
        planned here, unless their checkpoint loads (a batch killed while its files were written: finished from
        it). Returns the sound batches it holds, what was removed with why, and the lines to print."""
        said: Said = [(folders.claim(self.out, "sweep", {}, results.patterns(), overwrite), "--overwrite")]
        found, damaged = results.scan(self.out)
        clash = results.conflicts(found, batches)
        differ = {s: c for s, c in clash.items() if not c.stale}
        stale = {s: c for s, c in clash.items() if c.stale}
        if differ and not overwrite:
            raise ValueError(f"{self.out!r} refused: {results.describe(differ)}. Pass --overwrite to replace those "
                             "batches, or write to another folder")
        if stale and not (rerun_stale or overwrite):
            raise ValueError(f"{self.out!r} refused: {results.describe(stale)}. Pass --rerun-stale to run those "
                             "batches again with this implementation, or write to another folder")
        said += [(results.remove_batches(list(differ)), "--overwrite"),
                 (results.remove_batches(list(stale)), "stale (another implementation)")]
        if clash:  # the tables and figures describe removed runs
            said.append((results.remove_derived(self.out), "made of the replaced batches"))
        found = [(stem, saved) for stem, saved in found if stem not in clash]
        self.finished = len(found)
        planned = {results.stem(self.out, cfg): (cfg, keys) for cfg, keys in batches}
        lines = []
        for stem, e in damaged.items():
            if stem not in planned:
                lines.append(f"warning: {e}")
            elif self.loads(stem + results.PART, *planned[stem]):  # killed while it wrote the batch's files
                lines.append(f"{e}\nits batch is finished from its checkpoint {os.path.basename(stem + results.PART)}")
            else:
                kept = files.set_aside(results.batch_files(stem))
                lines.append(f"{e}\nits batch is run again; its files are kept as {', '.join(kept)}")
        return found, said, lines

    def loads(self, part: str, cfg: Config, keys: np.ndarray) -> bool:
        """Whether the batch checkpoint `part` (mqd-jax's, by the folder's manifest) loads as a batch of `cfg` and
        `keys`: a sound part, which a sweep continues (or finishes) and never sets aside."""
        if not (files.is_file(part) and os.path.basename(part) in manifest.written(self.out)):
            return False
        try:
            checkpoint.load(part, cfg, keys)
        except ValueError:
            return False
        return True

    def resumed_batch(self, part: str, cfg: Config, keys: np.ndarray, chunk: int, overwrite: bool, label: str
                      ) -> tuple[tuple[State, dict[str, np.ndarray]] | None, int, Said, list[str]]:
        """Where a batch starts: from its checkpoint `part` (an interrupted batch: its states, metrics and chunk
        size, so that it ends bit for bit as without the stop), or afresh (None, `chunk`). A damaged checkpoint is
        set aside; one of another config or keys is refused unless `overwrite`, which deletes it. Returns the
        start, the chunk size, what was removed with why, and the lines to print."""
        if not files.is_file(part) or os.path.basename(part) not in manifest.written(self.out):
            return None, chunk, [], []
        try:
            payload = checkpoint.read(part)
            began = payload.get("chunk")
            if not (isinstance(began, int) and began >= 1):
                raise checkpoint.Refused(part, "it records no chunk size")
        except ValueError as e:
            return None, chunk, [], [f"{e}\nthe batch starts afresh; its checkpoint is set aside as "
                                     f"{', '.join(files.set_aside([part]))}"]
        try:
            states, metrics = checkpoint.load(part, cfg, keys, payload)
        except checkpoint.Refused as e:
            if not overwrite:
                raise ValueError(f"{e}. Pass --overwrite to run the batch afresh (it deletes that checkpoint), or "
                                 "write to another folder") from None
            return None, chunk, [(folders.discard(self.out, [os.path.basename(part)]), "--overwrite")], []
        done = int(np.asarray(states.generation)[0])
        lines = []
        if began != chunk:
            lines.append(f"{label}continues in chunks of {began} generations, as it began (--chunk {chunk} is taken "
                         "by batches that start afresh), so that it ends bit for bit as without the stop")
        lines.append(f"{label}resuming at generation {done} of {cfg.max_generations} from {part}")
        return (states, metrics), began, [], lines
