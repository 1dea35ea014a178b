"""Results folders: one writer at a time, one config per folder, files written whole and checksummed.

* `lock(folder)`: held while a command writes a folder. A second writer is
  refused with a ValueError; the kernel releases the lock when its process ends,
  however it ends (`flock`), so a killed run leaves no stale lock.
* `claim(folder, kind, identity, patterns, overwrite)`: a folder records in
  `mqd.json` (its manifest) what wrote it (`kind`: "run" or "sweep", and the
  identity: config and seed), the provenance, and the name of every file
  mqd-jax has written in it (`write_atomically` adds each name before the file
  is written). Writing another identity into it is refused with the differing
  fields named, unless `overwrite`, which first removes the files the manifest
  lists, and nothing else: a user's own files in the folder are never removed.
* `write_atomically(path, data)`: a temporary file renamed over `path`, so a
  crash leaves the old file or the new one; leftovers of killed writers are
  removed when the folder is next locked.
* `write_json` / `read_json`, `write_npz` / `read_npz`: every JSON and npz file
  the library writes carries a SHA-256 checksum of its contents (JSON: the
  key "sha256"; npz: the array "sha256"), verified on every read. A file that
  cannot be read, has no checksum or does not match it raises `Damaged`
  (a ValueError) naming the file, what is wrong and how to repair it.
"""

from __future__ import annotations

import contextlib
import fcntl
import fnmatch
import glob
import hashlib
import io
import json
import os
import tempfile
import zipfile
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np
from flax import serialization

from mqd_jax.experiment.provenance import provenance

MANIFEST = "mqd.json"
LOCK = ".mqd.lock"
TMP_SUFFIX = ".mqdtmp"
CHECKSUM = "sha256"  # the key (JSON) or array (npz) that holds a file's checksum
_UMASK = os.umask(0o022)
os.umask(_UMASK)  # read, then restored: the process's umask is unchanged


class Damaged(ValueError):
    """A results file that cannot be used: unreadable, truncated, without checksum or altered.

    The message is one line: the file, what is wrong with it, and how to repair it.
    """

    def __init__(self, path: str, what: str, repair: str) -> None:
        super().__init__(f"{path!r} {what}: {repair}")
        self.path = path


def write_atomically(path: str, data: bytes) -> None:
    """Writes `data` to a temporary file and renames it over `path`: a crash leaves the old file or the new one.

    In a folder with a manifest (`claim`), the file's name is recorded in it first, so that `--overwrite` knows
    every file mqd-jax wrote there, a file interrupted halfway included.
    """
    _record(os.path.dirname(path) or ".", os.path.basename(path))
    fd, tmp = tempfile.mkstemp(prefix=os.path.basename(path) + ".", suffix=TMP_SUFFIX,
                               dir=os.path.dirname(path) or ".")
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)  # mkstemp makes the file private; results files get the usual mode
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def _strict(x: Any) -> Any:
    """`x` as strict JSON values: numpy arrays and scalars as lists and numbers, NaN as null."""
    if isinstance(x, dict):
        return {k: _strict(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_strict(v) for v in x]
    if isinstance(x, np.ndarray):
        return _strict(x.tolist())
    if isinstance(x, float) and x != x:
        return None
    return x.item() if isinstance(x, np.generic) else x


def _as_read(payload: Any) -> Any:
    """`payload` as JSON reads it back (tuples as lists, NaN as null, keys as strings)."""
    return json.loads(json.dumps(_strict(payload), allow_nan=False))


def _json_digest(payload: Any) -> str:
    """The SHA-256 of `payload` as canonical JSON (sorted keys, no spaces), as read back from a file."""
    return hashlib.sha256(json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()
                          ).hexdigest()


def write_json(path: str, payload: Mapping[str, Any]) -> None:
    """Writes the dict `payload` as strict JSON (NaN as null) with its checksum (key "sha256"), atomically."""
    if CHECKSUM in payload:
        raise ValueError(f"{path!r}: the key {CHECKSUM!r} is the file's checksum; give the payload another key")
    data = _as_read(dict(payload))
    write_atomically(path, json.dumps({**data, CHECKSUM: _json_digest(data)}).encode())


def read_json(path: str, repair: str) -> dict[str, Any]:
    """The dict `write_json` wrote to `path`, its checksum verified (and removed).

    Raises `Damaged` (naming the file, what is wrong and `repair`, the way to repair it) if the file cannot be read
    or parsed, is not a dict, carries no checksum or does not match it.
    """
    try:
        with open(path, "rb") as f:
            data = json.loads(f.read())
    except (OSError, ValueError) as e:  # ValueError: JSONDecodeError and UnicodeDecodeError
        raise Damaged(path, f"cannot be read ({type(e).__name__}: {e})", repair) from e
    if not (isinstance(data, dict) and isinstance(data.get(CHECKSUM), str)):
        raise Damaged(path, "carries no checksum (not written by mqd-jax 0.9.0 or later)", repair)
    digest = data.pop(CHECKSUM)
    if _json_digest(data) != digest:
        raise Damaged(path, "does not match its checksum: it was altered or damaged", repair)
    return data


def _npz_digest(arrays: Mapping[str, np.ndarray]) -> str:
    """The SHA-256 of the arrays' names, dtypes, shapes and bytes, in name order."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(json.dumps([name, a.dtype.str, list(a.shape)]).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def write_npz(path: str, **arrays: np.ndarray) -> None:
    """Writes `arrays` as a compressed `.npz` file at `path` with their checksum (array "sha256"), atomically."""
    if CHECKSUM in arrays:
        raise ValueError(f"{path!r}: the array {CHECKSUM!r} is the file's checksum; give the array another name")
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays, **{CHECKSUM: np.asarray(_npz_digest(arrays))})
    write_atomically(path, buffer.getvalue())


def read_npz(path: str, repair: str) -> dict[str, np.ndarray]:
    """The arrays `write_npz` wrote to `path`, their checksum verified (and removed); raises `Damaged` like
    `read_json`."""
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as e:
        raise Damaged(path, f"cannot be read ({type(e).__name__}: {e})", repair) from e
    digest = arrays.pop(CHECKSUM, None)
    if digest is None or digest.shape != () or digest.dtype.kind != "U":
        raise Damaged(path, "carries no checksum (not written by mqd-jax 0.9.0 or later)", repair)
    if _npz_digest(arrays) != str(digest):
        raise Damaged(path, "does not match its checksum: it was altered or damaged", repair)
    return arrays


def _make_folder(folder: str, create: bool) -> None:
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise ValueError(f"{folder!r} is a file, not a folder: give another --out")
    if not create and not os.path.isdir(folder):
        raise ValueError(f"{folder!r} does not exist: give the folder a `mqd sweep` or `mqd run` wrote")
    os.makedirs(folder, exist_ok=True)


@contextlib.contextmanager
def lock(folder: str, create: bool = True) -> Iterator[list[str]]:
    """Holds `folder`'s write lock (creating the folder if `create`, else refusing a missing one); yields the
    leftover temporary files it removed.

    Raises ValueError if another process holds it, or if the folder is missing and not `create`.
    """
    _make_folder(folder, create)
    path = os.path.join(folder, LOCK)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "unknown"
            raise ValueError(f"{folder!r} is being written by another mqd process (pid {holder}): wait for it to "
                             "finish, or write to another folder") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        leftovers = sorted(glob.glob(os.path.join(glob.escape(folder), "*" + TMP_SUFFIX)))
        for leftover in leftovers:  # no other writer can be writing them: we hold the lock
            os.remove(leftover)
        yield leftovers
    finally:
        os.close(fd)


def differences(saved: Mapping[str, Any], now: Mapping[str, Any]) -> str:
    """'field: saved A, now B' for every key whose values differ ('' if none)."""
    keys = sorted(set(saved) | set(now))
    return ", ".join(f"{k}: saved {saved.get(k)!r}, now {now.get(k)!r}" for k in keys if saved.get(k) != now.get(k))


def set_aside(paths: Sequence[str]) -> list[str]:
    """Renames each of `paths` that exists to `<path>.damaged` (or `.damaged-2`, ...); returns the new paths.

    What a command replaces because it is damaged is kept this way, never deleted: a damaged file may be a
    user's own file of the same name.
    """
    moved = []
    for path in paths:
        if not os.path.exists(path):
            continue
        target, n = path + ".damaged", 1
        while os.path.exists(target):
            n += 1
            target = f"{path}.damaged-{n}"
        os.replace(path, target)
        moved.append(target)
    return moved


def _manifest(folder: str) -> dict[str, Any] | None:
    """The manifest of `folder` (None if it has none); raises `Damaged` for a damaged one."""
    path = os.path.join(folder, MANIFEST)
    if not os.path.exists(path):
        return None
    saved = read_json(path, "pass --overwrite to replace the folder's results (only files mqd-jax wrote are "
                            "removed), or write to another folder")
    if not (isinstance(saved.get("identity"), dict) and isinstance(saved.get("written"), list)):
        raise Damaged(path, "is not an mqd-jax manifest", "remove it, or write to another folder")
    return saved


def _record(folder: str, name: str) -> None:
    """Adds `name` to the files the manifest of `folder` lists as written by mqd-jax (if it has a manifest)."""
    if name in (MANIFEST, LOCK):
        return
    saved = _manifest(folder)
    if saved is not None and name not in saved["written"]:
        saved["written"].append(name)
        write_json(os.path.join(folder, MANIFEST), saved)


def written(folder: str, saved: dict[str, Any] | None = None) -> list[str]:
    """The names of the files in `folder` that mqd-jax wrote there (its manifest's list, read unless `saved`
    gives it; [] without one)."""
    saved = _manifest(folder) if saved is None else saved
    return [] if saved is None else [n for n in saved["written"] if os.path.exists(os.path.join(folder, n))]


def _carries_provenance(path: str) -> bool:
    """Whether `path` is a results file of any mqd-jax version, recognised by the provenance in it (a folder
    without a manifest, written by mqd-jax before 0.9.0)."""
    try:
        if path.endswith(".json"):
            with open(path, "rb") as f:
                data = json.loads(f.read())
            return isinstance(data, dict) and ("provenance" in data or any(
                isinstance(v, dict) and "provenance" in v for v in data.values()))
        if path.endswith(".npz"):
            with np.load(path, allow_pickle=False) as f:
                return "meta" in f.files
        if path.endswith(".msgpack"):
            with open(path, "rb") as f:
                data = serialization.msgpack_restore(f.read())
            return isinstance(data, dict) and "format" in data
    except Exception:  # unreadable: not recognisably ours
        return False
    return path.endswith((".md", ".png"))  # tables and figures: made from the results, named as mqd-jax names them


def _matching(folder: str, patterns: Sequence[str]) -> list[str]:
    """The names of the files in `folder` that match the glob `patterns`."""
    names = os.listdir(folder) if os.path.isdir(folder) else []
    return sorted(n for n in names if any(fnmatch.fnmatchcase(n, p) for p in patterns))


def claim(folder: str, kind: str, identity: Mapping[str, Any], patterns: Sequence[str], overwrite: bool,
          upgrade: Callable[[dict[str, Any]], dict[str, Any]] | None = None) -> list[str]:
    """Makes `folder` the results folder of `identity` (call while holding its lock); returns the files removed.

    `patterns` are the glob patterns of the files this kind of command writes. The
    folder may already hold results of the same kind and identity (a run is then
    written again, a sweep continued). Anything else of ours in it (other
    identity, other kind, results without a manifest, a damaged manifest) is
    refused with a ValueError naming what differs, unless `overwrite`: then
    those results are removed first: the files the manifest lists or, without
    one, the files matching `patterns` that carry mqd-jax's provenance. A user's
    file is never removed: one whose name matches `patterns` is refused, even with
    `overwrite`, naming it. `upgrade` brings an identity saved by an earlier version to today's form before it
    is compared.
    """
    try:
        saved = _manifest(folder)
    except Damaged as e:
        if not overwrite:
            raise
        print(f"{e.path}: damaged manifest; --overwrite removes only the files mqd-jax recognisably wrote")
        saved = None
    named = _matching(folder, patterns)
    if saved is not None:
        ours = written(folder, saved)
    else:
        ours = [n for n in named if _carries_provenance(os.path.join(folder, n))]
    foreign = [n for n in named if n not in ours and n != MANIFEST]
    if foreign:
        raise ValueError(f"{folder!r} refused: {', '.join(foreign)} {'is' if len(foreign) == 1 else 'are'} not "
                         "written by mqd-jax here (not in its manifest mqd.json) but named like its results: move "
                         f"{'it' if len(foreign) == 1 else 'them'} away, or write to another folder")
    if saved is not None and upgrade is not None:
        saved["identity"] = upgrade(saved["identity"])
    if saved is not None and saved.get("kind") == kind and _as_read(saved.get("identity")) == _as_read(dict(identity)):
        return []
    if not ours:  # nothing to lose (a folder of ours whose run stopped before writing anything, or a new one)
        why = None
    elif saved is None:
        why = f"it holds results without a valid manifest ({ours[0]}, ...; from an mqd-jax older than 0.9.0?)"
    elif saved.get("kind") != kind:
        why = f"it holds the results of `mqd {saved.get('kind')}`"
    else:
        flat = lambda d: {**{k: v for k, v in d.items() if k != "config"}, **d.get("config", {})}  # noqa: E731
        why = f"it holds results of another run ({differences(flat(saved['identity']), flat(identity))})"
    if why is not None and not overwrite:
        raise ValueError(f"{folder!r} refused: {why}. Pass --overwrite to replace them (only files mqd-jax wrote "
                         "are removed), or write to another folder")
    removed = [os.path.join(folder, n) for n in ours] if why is not None else []
    for p in removed:
        os.remove(p)
    payload = {"kind": kind, "identity": dict(identity), "written": [] if why is not None else ours,
               "provenance": provenance()}
    write_json(os.path.join(folder, MANIFEST), payload)
    return removed

