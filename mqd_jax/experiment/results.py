"""A sweep's results folder: what `mqd sweep` and `mqd adapt` write, and the tables `mqd plot` makes of it.

One folder per sweep. For every task and algorithm run:

* `<task>_<algorithm>.json`: the config (every field), the seed keys, wall
  time, machine, provenance (versions, git revision) and every metric per seed
  and generation (`metrics[name]`: [seeds][generations]; NaN written as null).
* `<task>_<algorithm>.npz`: the final repertoires: `count` [S], `actions`
  [S, M, n], `behaviors` [S, M, d], `qualities` [S, M] (M: the largest count;
  rows past a seed's count are padding), and `meta` (the same config, keys and
  provenance, as a JSON string).
* `<task>_mqd.msgpack` (M-QD only): the final states, as a checkpoint
  (`mqd_jax.experiment.checkpoint`) with keys [S, 2]: what `mqd adapt` adapts.
* `<task>_<algorithm>.part.msgpack` while the batch runs: its states and
  metrics after each chunk (a checkpoint with keys [S, 2] and the chunk size),
  from which an interrupted batch resumes, bit for bit; removed once the batch
  is saved.

`mqd adapt` adds `adaptation.json` ({task: {"source": the SHA-256 of the
`<task>_mqd.msgpack` it adapted, "config", "keys", "provenance", "methods":
{method: {"error", "steps", "reached"}: one value per repertoire}}}). Tables and figures (`DERIVED`) are
markdown and PNG built from these files only, so a folder can be copied and
re-tabulated anywhere.

Every JSON and npz file carries its checksum (`mqd_jax.experiment.folders`), verified on
every read; each batch also records its `implementation`: the mqd-jax version
and which implementation of the task ran (`mqd_jax.core.registry.source`).

A folder never mixes configs: the batches of one task share their config (but
for the algorithm), their seed keys and their implementation (`scan` finds
batches that do not, and damaged ones; `load_runs` refuses such a folder), and
adaptation results of M-QD runs that have since changed are left out of the
tables and figures (`adaptation`).
"""

from __future__ import annotations

import dataclasses
import fnmatch
import glob
import hashlib
import json
import os
from typing import Any

import jax
import numpy as np

from mqd_jax.core import algorithms, registry
from mqd_jax.core.config import Config
from mqd_jax.core.state import State, get_task
from mqd_jax.experiment import checkpoint, files, manifest, messages, migrations
from mqd_jax.experiment.files import Damaged, read_json, read_npz
from mqd_jax.experiment.folders import differences, write_json, write_npz
from mqd_jax.experiment.manifest import remove_written
from mqd_jax.experiment.provenance import machine, provenance
from mqd_jax.version import __version__

# The tables and figures made from a sweep folder's files.
DERIVED = ("table1.md", "adaptation.md", "fig2_*.png", "fig3_adaptation_error.png", "fig4_adaptation_steps.png")
ADAPTATION = "adaptation.json"
# What a batch's JSON holds besides its metrics.
BATCH_KEYS = ("config", "keys", "implementation", "provenance", "wall_s", "machine", "metrics")


def _batch_patterns(task: str = "*") -> list[str]:
    """Glob patterns of the batches' JSON and npz files (of one task, or of all)."""
    return [f"{glob.escape(file_name(task)) if task != '*' else '*'}_{a}.{ext}" for a in algorithms.names()
            for ext in ("json", "npz")]


def patterns() -> tuple[str, ...]:
    """The files a sweep folder holds (glob patterns, for `folders.claim`) and those made from them."""
    return (*_batch_patterns(), "*_mqd.msgpack", *(f"*_{a}{PART}" for a in algorithms.names()), ADAPTATION,
            *DERIVED)


PART = ".part.msgpack"  # a running batch's checkpoint: `<task>_<algorithm>.part.msgpack`


def file_name(task: str) -> str:
    """`task` as it appears in file names (plugin names "package.module:factory" become "package.module.factory")."""
    return task.replace(":", ".").replace(os.sep, ".")


def _stem(out: str, task: str, algorithm: str) -> str:
    return os.path.join(out, f"{file_name(task)}_{algorithm}")


def stem(out: str, cfg: Config) -> str:
    """The path, without extension, of the batch of `cfg`'s runs in `out`."""
    return _stem(out, cfg.task_name, cfg.algorithm_name)


def implementation(cfg: Config) -> dict[str, str]:
    """{"mqd_jax": the version, "task": which implementation of the task} that runs of `cfg` are made by."""
    named = registry.name_of(cfg.task)
    task = registry.source(named[0]) if named else f"{type(cfg.task).__module__}.{type(cfg.task).__qualname__}"
    return {"mqd_jax": __version__, "task": task}


def repair(out: str, stem: str) -> str:
    """How to repair a damaged batch `stem` of the folder `out`: the command that re-runs it (shell-quoted)."""
    task, _, algorithm = os.path.basename(stem).rpartition("_")
    command = messages.command("mqd", "sweep", "--tasks", task, "--algorithms", algorithm, ("--out", out))
    return f"`{command}` with the flags that made it re-runs it (a damaged batch is re-run)"


def missing(out: str) -> list[tuple[str, str]]:
    """(task, algorithm) of each batch a `mqd sweep` planned in `out` (its manifest) that is not there."""
    return [(e["task"], e["algorithm"]) for e in manifest.planned(out)
            if isinstance(e.get("task"), str) and isinstance(e.get("algorithm"), str)
            and not files.lexists(_stem(out, e["task"], e["algorithm"]) + ".json")]


def npz_bytes(cfg: Config, runs: int = 1) -> int:
    """The most bytes the npz of `runs` final repertoires of `cfg` may hold (float32 actions, behaviors and
    qualities of `capacity` skills, a count per run, and `files.NPZ_SLACK` for its meta text): what a read of one
    allocates at most."""
    task = get_task(cfg)
    return runs * (cfg.capacity * (task.action_dim + task.behavior_dim + 1) + 1) * 8 + files.NPZ_SLACK


def _batch_config(saved: dict[str, Any], path: str, fix: str) -> Config:
    """The config a batch's JSON holds; raises `Damaged` (naming `path`) for one that is not a valid config."""
    try:
        return migrations.config_from(saved["config"])
    except (TypeError, ValueError, KeyError, AttributeError) as e:
        raise Damaged(path, f"holds an invalid config ({type(e).__name__}: {e})", fix) from e


def _read_batch(out: str, stem: str) -> dict[str, Any]:
    """The saved JSON of the batch `stem`, every file of it verified (checksums, contents, sizes bounded by its
    config); raises `Damaged`."""
    fix = repair(out, stem)
    saved = read_json(stem + ".json", fix)
    missing = [k for k in BATCH_KEYS if k not in saved]
    if missing:
        raise Damaged(stem + ".json", f"lacks {', '.join(map(repr, missing))} (not a complete batch of `mqd sweep`)",
                      fix)
    if not (isinstance(saved["config"], dict) and isinstance(saved["keys"], list)):
        raise Damaged(stem + ".json", "holds a config or keys of the wrong type", fix)
    cfg = _batch_config(saved, stem + ".json", fix)
    if not files.lexists(stem + ".npz"):
        raise Damaged(stem + ".npz", "is missing", fix)
    arrays = read_npz(stem + ".npz", fix, npz_bytes(cfg, len(saved["keys"])))
    if "meta" not in arrays or json.loads(str(arrays["meta"])).get("keys") != saved["keys"]:
        raise Damaged(stem + ".npz", f"does not belong to {os.path.basename(stem)}.json (other keys)", fix)
    if stem.endswith("_mqd"):
        try:
            checkpoint.read(stem + ".msgpack")
        except ValueError as e:
            raise Damaged(stem + ".msgpack", f"is missing or damaged ({e})", fix) from e
    saved["config"] = migrations.upgraded(saved["config"])
    return saved


def scan(out: str, task: str = "*") -> tuple[list[tuple[str, dict[str, Any]]], dict[str, Damaged]]:
    """The batches in `out` (of one task, or of all): [(stem, saved JSON)] of the sound ones, and {stem: Damaged}
    of the damaged ones (a file unreadable, missing, altered, or without checksum). Reads and verifies every file
    of them: scan once, and pass the batches on (`conflicts`, `is_done`)."""
    found, damaged = [], {}
    names = {n for n in files.listdir(out) for pattern in _batch_patterns(task) if fnmatch.fnmatchcase(n, pattern)}
    for stem in sorted({os.path.join(out, n.rsplit(".", 1)[0]) for n in names}, key=lambda s: s + ".json"):
        try:
            found.append((stem, _read_batch(out, stem)))
        except Damaged as e:
            damaged[stem] = e
    return found, damaged


def _comparable(cfg: dict[str, Any], other: dict[str, Any]) -> dict[str, Any]:
    """The settings of `cfg` that must agree with `other`'s, a batch of the same task: every field but the
    algorithm, and of its options those that `other`'s preset takes too (a QD batch may sit beside an M-QD batch
    of any ensemble size, but both must vary with the same iso_sigma)."""
    options, others = cfg.get("algorithm_options", {}), other.get("algorithm_options", {})
    shared = {f"algorithm_options.{k}": v for k, v in options.items() if k in others}
    return {**{k: v for k, v in cfg.items() if k not in ("algorithm", "algorithm_options")}, **shared}


@dataclasses.dataclass(frozen=True)
class Clash:
    """Why a batch may not sit beside another of its task: `stale` (written by another mqd-jax version or another
    implementation of the task: `--rerun-stale` re-runs it) or not (another config or other keys: `--overwrite`)."""

    stale: bool
    why: str


def _clashes(batches: list[tuple[str, dict[str, Any]]], cfg: dict[str, Any], keys: list,
             made_by: dict[str, str]) -> dict[str, Clash]:
    """{stem: Clash} for each of `batches` of the same task as `cfg` with another config, other keys, or another
    implementation (`made_by`) than theirs."""
    found = {}
    for stem, saved in batches:
        task = saved["config"].get("task")
        if task != cfg["task"] and isinstance(task, str) and isinstance(cfg["task"], str) and \
                file_name(task) == file_name(cfg["task"]):
            found[stem] = Clash(False, f"task: saved {task!r}, now {cfg['task']!r}, one file name "
                                       f"{file_name(task)!r}")
        if task != cfg["task"]:
            continue
        differ = differences(_comparable(saved["config"], cfg), _comparable(cfg, saved["config"]))
        if saved["keys"] != keys:
            differ = ", ".join(filter(None, [differ, f"{len(saved['keys'])} other seed keys, now {len(keys)}"]))
        if differ:
            found[stem] = Clash(False, differ)
        elif saved["implementation"] != made_by:
            found[stem] = Clash(True, differences(saved["implementation"], made_by))
    return found


def conflicts(batches: list[tuple[str, dict[str, Any]]], planned: list[tuple[Config, np.ndarray]]) -> dict[str, Clash]:
    """{stem: Clash} for each of a folder's sound `batches` (`scan`) that one of the `planned` batches (config,
    keys) may not sit beside: the batches of one task must share their config (the algorithm aside), their keys
    and their implementation.
    """
    return {stem: clash for cfg, keys in planned
            for stem, clash in _clashes(batches, cfg.to_dict(), np.asarray(keys).tolist(), implementation(cfg)).items()}


def describe(clash: dict[str, Clash]) -> str:
    """'<batch> differs (<fields>); ...' for the clashing batches of `conflicts`."""
    return "; ".join(f"{os.path.basename(stem)} {'is stale' if c.stale else 'differs'} ({c.why})"
                     for stem, c in clash.items())


def batch_files(stem: str) -> list[str]:
    """The files of the batch `stem` that the folder's manifest lists as mqd-jax's (JSON, npz, M-QD states, the
    running batch's checkpoint): never a user's file of such a name."""
    ours = set(manifest.written(os.path.dirname(stem) or "."))
    return [stem + ext for ext in (".json", ".npz", ".msgpack", PART) if os.path.basename(stem + ext) in ours]


def remove_batches(stems: list[str]) -> list[str]:
    """Removes these batches (the files `batch_files` lists); returns the files removed. Adaptation results of
    removed M-QD runs turn stale."""
    removed = [p for stem in stems for p in batch_files(stem)]
    for path in removed:
        files.remove(path)
    return removed


def is_done(batches: list[tuple[str, dict[str, Any]]], out: str, cfg: Config, keys: np.ndarray) -> bool:
    """Whether a folder's sound `batches` (`scan(out)`) hold the runs of `cfg` from exactly these keys, made by
    this implementation."""
    saved = dict(batches).get(stem(out, cfg))
    return (saved is not None and saved["config"] == cfg.to_dict() and saved["keys"] == np.asarray(keys).tolist()
            and saved["implementation"] == implementation(cfg))


def remove_derived(out: str) -> list[str]:
    """Removes the tables and figures mqd-jax made from `out`'s results (they are remade from the files by
    `mqd plot`): those its manifest lists, never a file of the user's named like them; returns their paths."""
    return remove_written(out, DERIVED)


def save_runs(out: str, cfg: Config, keys: np.ndarray, states: State, metrics: dict[str, np.ndarray],
              wall_s: float) -> None:
    """Writes a batch of runs of `cfg` (states and metrics with a leading seed axis) to the folder `out`.

    Raises ValueError if `out` holds batches that conflict with it (`conflicts`),
    or if `cfg` is not a preset of a registered task (a folder's files are read
    back by name; save other runs with `mqd_jax.experiment.checkpoint.save`); removes the
    tables and figures made from the folder's earlier results.
    """
    if cfg.algorithm not in algorithms.names() or registry.name_of(cfg.task) is None:
        raise ValueError(f"a results folder holds the algorithms {algorithms.names()} of registered tasks, not "
                         f"{cfg.algorithm!r} on {cfg.task!r}: save such runs with mqd_jax.experiment.checkpoint.save")
    clash = conflicts(scan(out, cfg.task_name)[0], [(cfg, keys)])
    if clash:
        raise ValueError(f"{out!r} refused: {describe(clash)}")
    files.make_folder(out)
    remove_derived(out)
    path = stem(out, cfg)
    meta = {"config": cfg.to_dict(), "keys": np.asarray(keys).tolist(), "implementation": implementation(cfg),
            "provenance": provenance()}
    rep = jax.device_get(states.repertoire)
    m = max(int(rep.count.max()), 1)
    write_npz(path + ".npz", count=rep.count, actions=rep.actions[:, :m], behaviors=rep.behaviors[:, :m],
              qualities=rep.qualities[:, :m], meta=np.asarray(json.dumps(meta)))
    if cfg.algorithm == "mqd":
        checkpoint.save(path + ".msgpack", states, metrics, cfg, keys)
    # The JSON last: a batch without it is not complete (`scan` reports it damaged, and a sweep runs it again).
    write_json(path + ".json", {**meta, "wall_s": wall_s, "machine": machine(), "metrics": metrics})
    remove_written(out, [glob.escape(os.path.basename(path) + PART)])  # the batch is whole: its checkpoint goes


@dataclasses.dataclass(frozen=True)
class Runs:
    """The runs of one task and algorithm, as read back from a results folder.

    Attributes:
      cfg: their config.
      keys: [S, 2] seed keys.
      wall_s: wall time of the batch (compilation included).
      machine: where it ran.
      metrics: name -> [S, G] float array (NaN where null).
      count: [S] final repertoire sizes.
      behaviors: [S, M, d] final behaviors (rows past count: padding).
      qualities: [S, M] their qualities (rows past count: padding).
    """

    cfg: Config
    keys: np.ndarray
    wall_s: float
    machine: str
    metrics: dict[str, np.ndarray]
    count: np.ndarray
    behaviors: np.ndarray
    qualities: np.ndarray

    def final(self, name: str) -> np.ndarray:
        """[S] the metric `name` after the last generation."""
        return self.metrics[name][:, -1]


def task_order(task: str) -> int:
    """Sort key: the registry's order (entry points, then tasks registered in Python), then the rest."""
    return (*registry.registered_tasks(), task).index(task)


def load_runs(out: str) -> dict[str, dict[str, Runs]]:
    """{task: {algorithm: Runs}} for every batch of runs in `out` (tasks in registry order).

    Raises ValueError, naming the file and the command that re-runs it, for a
    damaged batch (a file unreadable, missing, altered or without checksum), and
    for batches of one task that differ in config (but for the algorithm), seed
    keys or implementation (mqd-jax version, the task's source).
    """
    found: dict[str, dict[str, Runs]] = {}
    batches, damaged = scan(out)
    if damaged:
        raise next(iter(damaged.values()))
    for stem, saved in batches:
        try:
            cfg = Config.from_dict(saved["config"])
        except (TypeError, ValueError) as e:
            raise ValueError(f"{stem + '.json'!r} holds an invalid config: {e}") from e
        clash = _clashes(batches, saved["config"], saved["keys"], saved["implementation"])
        if clash:
            raise ValueError(f"{out!r} mixes runs that cannot be compared: beside {os.path.basename(stem)}, "
                             f"{describe(clash)}; `mqd sweep` with --rerun-stale (another implementation) or "
                             "--overwrite (another config) in this folder repairs it")
        rep = read_npz(stem + ".npz", repair(out, stem), npz_bytes(cfg, len(saved["keys"])))
        metrics = {k: np.array(v, dtype=float) for k, v in saved["metrics"].items()}
        found.setdefault(cfg.task_name, {})[cfg.algorithm] = Runs(
            cfg, np.asarray(saved["keys"], np.uint32), saved["wall_s"], saved["machine"], metrics, rep["count"],
            rep["behaviors"], rep["qualities"])
    if not found:
        raise ValueError(f"{out!r} holds no sweep results (<task>_<algorithm>.json with .npz): run `mqd sweep` first")
    return {task: dict(sorted(found[task].items(), key=lambda kv: algorithms.names().index(kv[0])))
            for task in sorted(found, key=task_order)}


def load_states(out: str, task: str) -> tuple[Config, np.ndarray, State]:
    """The config, seed keys [S, 2] and final M-QD states (leading axis S) of `task` in `out`."""
    stem = _stem(out, task, "mqd")
    if not files.lexists(stem + ".json"):
        raise ValueError(f"{out!r} has no M-QD runs of {task!r}: run "
                         f"`{messages.command('mqd', 'sweep', '--tasks', task, ('--out', out))}` with M-QD first")
    saved = _read_batch(out, stem)
    cfg, keys = Config.from_dict(saved["config"]), np.asarray(saved["keys"], np.uint32)
    state, _ = checkpoint.load(stem + ".msgpack", cfg, keys)
    return cfg, keys, state


def source(out: str, task: str) -> str:
    """The SHA-256 of `task`'s final M-QD states in `out`: what an adaptation result was computed from."""
    return hashlib.sha256(files.read_bytes(_stem(out, task, "mqd") + ".msgpack")).hexdigest()


def read_adaptation(out: str) -> dict[str, Any]:
    """The contents of `out`'s adaptation.json ({} if none); raises `Damaged` for a damaged one."""
    path = os.path.join(out, ADAPTATION)
    return read_json(path, f"`mqd adapt {out}` (every task) writes it anew") if files.lexists(path) else {}


def adaptation(out: str) -> tuple[dict[str, Any], list[str]]:
    """The adaptation results in `out` whose M-QD runs are still there unchanged, and the tasks left out.

    Returns ({task: {method: results}} in registry order, [tasks whose results are stale]). Raises `Damaged`
    for a damaged adaptation.json.
    """
    current, stale = {}, []
    for task, entry in read_adaptation(out).items():
        fresh = (isinstance(entry, dict) and files.is_file(_stem(out, task, "mqd") + ".msgpack")
                 and entry.get("source") == source(out, task))
        if fresh:
            current[task] = entry["methods"]
        else:
            stale.append(task)
    return {t: current[t] for t in sorted(current, key=task_order)}, stale


