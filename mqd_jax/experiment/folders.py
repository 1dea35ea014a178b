"""Results folders: one writer at a time, one config per folder, files written whole and checksummed.

* `lock(folder)`: held while a command writes a folder. A second writer is
  refused with a ValueError; the kernel releases the lock when its process ends,
  however it ends (`flock`), so a killed run leaves no stale lock, and a process
  that ends normally removes the lock file. The lock file is never followed: a
  symbolic link, a file with other hard links or anything but a regular file in
  its place is refused, so taking the lock cannot write anywhere else.
* `claim(folder, kind, identity, patterns, overwrite)`: a folder records in
  `mqd.json` (its manifest) what wrote it (`kind`: "run" or "sweep", and the
  identity: config and seed), the provenance, and the name of every file
  mqd-jax has written in it (`write_atomically` adds each name before the file
  is written). Writing another identity into it is refused with the differing
  fields named, unless `overwrite`, which first removes the files the manifest
  lists, and nothing else: a user's own files in the folder are never removed.
  A manifest entry must be a plain file name directly in the folder (no path,
  no `..`, no link): anything else makes the manifest damaged, so no command
  ever removes or writes a file outside its folder. In a folder with a manifest,
  `write_atomically` refuses to replace a file the manifest does not list.
* `write_atomically(path, data)`: a temporary file renamed over `path`, so a
  crash leaves the old file or the new one; leftovers of killed writers (the
  temporary files of names the manifest lists) are removed when the folder is
  next locked.
* `write_json` / `read_json`, `write_npz` / `read_npz`: every JSON and npz file
  the library writes carries a SHA-256 checksum of its contents (JSON: the
  key "sha256"; npz: the array "sha256"), verified on every read. A file that
  cannot be read, has no checksum or does not match it raises `Damaged`
  (a ValueError) naming the file, what is wrong and how to repair it; so does a
  JSON file with NaN or Infinity literals (not JSON) or nested too deep to read.
  Infinite values are written as the strings "Infinity" and "-Infinity" (JSON
  has no number for them), with a warning naming the key that holds them.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import fnmatch
import hashlib
import io
import json
import math
import os
import re
import stat
import tempfile
import warnings
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
    every file mqd-jax wrote there, a file interrupted halfway included; a file already there that the manifest
    does not list (a user's) is refused with a ValueError, never replaced.
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


def _strict(x: Any, where: str = "", infinite: set[str] | None = None) -> Any:
    """`x` as strict JSON values: numpy arrays and scalars as lists and numbers, NaN as null, +-inf as the strings
    "Infinity" and "-Infinity"; the keys (dotted) that hold infinite values are added to `infinite`."""
    if isinstance(x, dict):
        return {k: _strict(v, f"{where}.{k}" if where else str(k), infinite) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_strict(v, where, infinite) for v in x]
    if isinstance(x, np.ndarray):
        return _strict(x.tolist(), where, infinite)
    x = x.item() if isinstance(x, np.generic) else x
    if isinstance(x, float) and x != x:
        return None
    if isinstance(x, float) and x in (math.inf, -math.inf):
        if infinite is not None:
            infinite.add(where or "the value")
        return "Infinity" if x > 0 else "-Infinity"
    return x


def _as_read(payload: Any, infinite: set[str] | None = None) -> Any:
    """`payload` as JSON reads it back (tuples as lists, NaN as null, +-inf as strings, keys as strings)."""
    return json.loads(json.dumps(_strict(payload, infinite=infinite), allow_nan=False))


def _json_digest(payload: Any) -> str:
    """The SHA-256 of `payload` as canonical JSON (sorted keys, no spaces), as read back from a file."""
    return hashlib.sha256(json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()
                          ).hexdigest()


class InfiniteValues(UserWarning):
    """A results file holds infinite values (written as the strings "Infinity" and "-Infinity")."""


def _not_json(literal: str) -> Any:
    """`json.loads`' parse_constant: NaN, Infinity and -Infinity are not JSON (mqd-jax writes none of them)."""
    raise ValueError(f"the literal {literal} is not JSON")


def write_json(path: str, payload: Mapping[str, Any]) -> None:
    """Writes the dict `payload` as strict JSON (NaN as null) with its checksum (key "sha256"), atomically."""
    if CHECKSUM in payload:
        raise ValueError(f"{path!r}: the key {CHECKSUM!r} is the file's checksum; give the payload another key")
    infinite: set[str] = set()
    data = _as_read(dict(payload), infinite)
    if infinite:
        warnings.warn(f"{path}: {', '.join(sorted(infinite))} hold infinite values, written as the strings "
                      '"Infinity"/"-Infinity" (JSON has no number for them)', InfiniteValues, stacklevel=2)
    write_atomically(path, json.dumps({**data, CHECKSUM: _json_digest(data)}).encode())


def read_json(path: str, repair: str) -> dict[str, Any]:
    """The dict `write_json` wrote to `path`, its checksum verified (and removed).

    Raises `Damaged` (naming the file, what is wrong and `repair`, the way to repair it) if the file cannot be read
    or parsed (NaN and Infinity literals are not JSON; nesting too deep to read), is not a dict, carries no checksum
    or does not match it.
    """
    try:
        with open(path, "rb") as f:
            data = json.loads(f.read(), parse_constant=_not_json)
    except RecursionError as e:
        raise Damaged(path, "cannot be read (nested too deep)", repair) from e
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
    if os.path.islink(folder) and not os.path.exists(folder):
        raise ValueError(f"{folder!r} is a symbolic link to nothing: give another --out, or make the folder it "
                         "points to")
    if not create and not os.path.isdir(folder):
        raise ValueError(f"{folder!r} does not exist: give a folder that `mqd sweep` wrote")
    os.makedirs(folder, exist_ok=True)


def _open_lock(path: str) -> int:
    """The lock file `path`, opened (created if missing) and locked: never through a link, only a regular file of
    one name. Raises ValueError if another process holds it or the path is not such a file."""
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o644)
        except OSError as e:
            if e.errno != errno.ELOOP:
                raise
            raise ValueError(f"{path!r} is a symbolic link, not mqd-jax's lock file (mqd-jax never follows it): "
                             "remove it") from None
        opened = os.fstat(fd)
        if not stat.S_ISREG(opened.st_mode) or opened.st_nlink != 1:
            os.close(fd)
            what = "a file with other hard links" if stat.S_ISREG(opened.st_mode) else "not a regular file"
            raise ValueError(f"{path!r} is not mqd-jax's lock file ({what}): remove it")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise ValueError(f"{os.path.dirname(path)!r} is being written by another mqd process (pid {holder}): "
                             "wait for it to finish, or write to another folder") from None
        try:  # a holder that finished removed the file we opened: lock the one the path names now
            now = os.stat(path, follow_symlinks=False)
        except FileNotFoundError:
            now = None
        if now is not None and (now.st_dev, now.st_ino) == (opened.st_dev, opened.st_ino):
            return fd
        os.close(fd)


def _leftovers(folder: str) -> list[str]:
    """The temporary files that killed writers left in `folder`: those of the names its manifest lists (and of
    the manifest itself); [] for a folder without a sound manifest (nothing there is known to be ours)."""
    try:
        saved = _manifest(folder)
    except Damaged:
        saved = None
    if saved is None:
        return []
    ours = {MANIFEST, *saved["written"]}
    made = re.compile(r"(.+)\.[A-Za-z0-9_]{8}" + re.escape(TMP_SUFFIX))  # tempfile.mkstemp's names
    return sorted(os.path.join(folder, n) for n in os.listdir(folder)
                  if (m := made.fullmatch(n)) and m.group(1) in ours)


@contextlib.contextmanager
def lock(folder: str, create: bool = True) -> Iterator[list[str]]:
    """Holds `folder`'s write lock (creating the folder if `create`, else refusing a missing one); yields the
    leftover temporary files of killed writers it removed. The lock file is removed when the lock is released.

    Raises ValueError if another process holds it, if the folder is missing and not `create`, or if the lock
    file's path is anything but a regular file (a link is never followed).
    """
    _make_folder(folder, create)
    path = os.path.join(folder, LOCK)
    fd = _open_lock(path)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        leftovers = _leftovers(folder)
        for leftover in leftovers:  # no other writer can be writing them: we hold the lock
            os.remove(leftover)
        yield leftovers
    finally:
        with contextlib.suppress(OSError):  # still ours (we hold its lock): nobody else can be using it
            os.remove(path)
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


def _plain_name(name: Any) -> bool:
    """Whether `name` is a plain file name: a string naming a file directly in a folder (no path, no `..`)."""
    return (isinstance(name, str) and name not in ("", ".", "..") and "/" not in name and os.sep not in name
            and "\0" not in name and (os.altsep is None or os.altsep not in name))


def _manifest(folder: str) -> dict[str, Any] | None:
    """The manifest of `folder` (None if it has none); raises `Damaged` for a damaged one, and for one that names
    anything but plain file names of the folder's regular files (a path, `..`, a folder or a link)."""
    path = os.path.join(folder, MANIFEST)
    if not os.path.lexists(path):
        return None
    repair = ("pass --overwrite to replace the folder's results (only files mqd-jax recognisably wrote are "
              "removed), or write to another folder")
    saved = read_json(path, repair)
    if not (isinstance(saved.get("identity"), dict) and isinstance(saved.get("written"), list)):
        raise Damaged(path, "is not an mqd-jax manifest", "remove it, or write to another folder")
    for name in saved["written"]:
        if not _plain_name(name) or name in (MANIFEST, LOCK):
            raise Damaged(path, f"lists {name!r}, which is not a plain file name of the folder", repair)
        full = os.path.join(folder, name)
        if os.path.lexists(full) and (os.path.islink(full) or not os.path.isfile(full)):
            raise Damaged(path, f"lists {name!r}, which is {'a link' if os.path.islink(full) else 'not a file'} "
                          "(mqd-jax writes only files)", repair)
    return saved


def _record(folder: str, name: str) -> None:
    """Adds `name` to the files the manifest of `folder` lists as written by mqd-jax (if it has a manifest);
    refuses (ValueError) a file already there that the manifest does not list: it is not ours to replace."""
    if name in (MANIFEST, LOCK):
        return
    saved = _manifest(folder)
    if saved is not None and name not in saved["written"]:
        if os.path.lexists(os.path.join(folder, name)):
            raise ValueError(f"{os.path.join(folder, name)!r} is not written by mqd-jax here (not in its manifest "
                             f"{MANIFEST}), so it is not replaced: move it away, or write to another folder")
        saved["written"].append(name)
        write_json(os.path.join(folder, MANIFEST), saved)


def plan(folder: str, planned: Sequence[Mapping[str, Any]]) -> None:
    """Adds `planned` (what a command is about to write, e.g. a sweep's batches) to the manifest of `folder` (key
    "planned"; call holding its lock, after `claim`), so that what is missing after an interruption can be named."""
    saved = _manifest(folder)
    if saved is None:
        raise ValueError(f"{folder!r} has no manifest: claim it first")
    entries = list(saved.get("planned", []))
    entries += [e for e in _as_read(list(planned)) if e not in entries]
    if entries != saved.get("planned"):
        write_json(os.path.join(folder, MANIFEST), {**saved, "planned": entries})


def planned(folder: str) -> list[dict[str, Any]]:
    """What the manifest of `folder` says was planned (`plan`); [] without a sound manifest."""
    try:
        saved = _manifest(folder)
    except Damaged:
        return []
    entries = [] if saved is None else saved.get("planned", [])
    return [e for e in entries if isinstance(e, dict)] if isinstance(entries, list) else []


def kind(folder: str) -> str | None:
    """What wrote `folder`, as its manifest says ("run" or "sweep"); None without a sound manifest."""
    try:
        saved = _manifest(folder)
    except Damaged:
        return None
    return None if saved is None else saved.get("kind")


def written(folder: str, saved: dict[str, Any] | None = None) -> list[str]:
    """The names of the files in `folder` that mqd-jax wrote there (its manifest's list, read unless `saved`
    gives it; [] without one)."""
    saved = _manifest(folder) if saved is None else saved
    return [] if saved is None else [n for n in saved["written"] if os.path.exists(os.path.join(folder, n))]


def remove_written(folder: str, patterns: Sequence[str]) -> list[str]:
    """Removes the files of `folder` that match the glob `patterns` and that its manifest lists as written by
    mqd-jax (nothing in a folder without a manifest); returns their paths. A user's file is never removed."""
    removed = [os.path.join(folder, n) for n in written(folder) if any(fnmatch.fnmatchcase(n, p) for p in patterns)]
    for path in removed:
        os.remove(path)
    return removed


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
        print(f"{e}\n--overwrite removes only the files mqd-jax recognisably wrote and writes a new manifest")
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

