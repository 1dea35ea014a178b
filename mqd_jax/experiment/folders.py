"""Results folders: one writer at a time, one config per folder, files written whole and checksummed.

* Pinned: `lock(folder)` opens the folder once (a directory descriptor) and,
  while it is held, every read, write, rename and removal of a file of that
  folder (`os.path.join(folder, name)` given to any function here) goes
  relative to that descriptor, never through the path again: a folder renamed
  or replaced under a running command (`mv R R.orig; mkdir R`, or a link
  swapped in) cannot redirect a single byte: the command finishes in the folder
  it started in, and says where that folder now is when it no longer sits at
  its path. Results files are only ever regular files: every open is
  non-blocking and never follows a link, so a FIFO, a device or a link named
  like a result is refused, naming it, instead of hanging a command.
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
  lists (those that fail their checks, `check`, are set aside as `.damaged`,
  never deleted), and nothing else: a user's own files in the folder are never
  removed. A folder without a sound manifest loses only files mqd-jax can prove
  it wrote (JSON, npz, msgpack and PNG files carrying its provenance); anything
  else named like a result (a table, a link, a folder, a FIFO) is refused with
  the list, even with `overwrite`.
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
  Reads are bounded: `read_npz` checks every member's declared and inflated
  size and its npy header against the bytes the caller's config implies
  (`max_bytes`) before reading it, and a JSON file larger than `MAX_JSON` is
  refused unread. The checksum guards against accidents (a truncated or
  altered file), not against a forger, who can compute a new one: what a
  file's contents must satisfy is checked by its reader.
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
import secrets
import stat
import sys
import warnings
import zipfile
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import IO, Any

import numpy as np
from flax import serialization

from mqd_jax.experiment.provenance import provenance

MANIFEST = "mqd.json"
LOCK = ".mqd.lock"
TMP_SUFFIX = ".mqdtmp"
CHECKSUM = "sha256"  # the key (JSON) or array (npz) that holds a file's checksum
MAX_JSON = 2**30  # the largest JSON file read (bytes): a sweep of 25 seeds x 10,000 generations is under 200 MB
MAX_DEPTH = 64  # the deepest nesting of lists and dicts read from a JSON file (mqd-jax's nest a few levels)
NPZ_SLACK = 2**24  # bytes an npz may hold beyond the arrays its config implies (its `meta` text)
# Folders pinned by `lock`: absolute path as given -> the descriptor every file operation in it goes through.
_PINNED: dict[str, int] = {}


class Damaged(ValueError):
    """A results file that cannot be used: unreadable, truncated, without checksum or altered.

    The message is one line: the file, what is wrong with it, and how to repair it.
    """

    def __init__(self, path: str, what: str, repair: str) -> None:
        super().__init__(f"{path!r} {what}: {repair}")
        self.path = path


class NotAFile(ValueError):
    """A path named like a results file that is not a regular file (a FIFO, a device, a folder or a link)."""

    def __init__(self, path: str, what: str) -> None:
        super().__init__(f"{path!r} is {what}, not a regular file: mqd-jax reads and writes only regular files "
                         "(and never follows a link there); move it away, or write to another folder")
        self.path = path


def _at(path: str) -> tuple[int | None, str]:
    """(descriptor, name) of `path` in a pinned folder, else (None, path): what the `dir_fd` calls take."""
    fd = _PINNED.get(os.path.abspath(os.path.dirname(path) or "."))
    return (None, path) if fd is None else (fd, os.path.basename(path))


def make_folder(folder: str) -> None:
    """Makes `folder` (and its parents) unless it is pinned (`lock`): a pinned folder is there, wherever it sits."""
    if os.path.abspath(folder) not in _PINNED:
        os.makedirs(folder, exist_ok=True)


def _lstat(path: str) -> os.stat_result | None:
    """The path's own status (a link's, not its target's); None if nothing is there."""
    fd, name = _at(path)
    try:
        return os.stat(name, dir_fd=fd, follow_symlinks=False)
    except FileNotFoundError:
        return None


def lexists(path: str) -> bool:
    """Whether anything (a file, a link, a folder ...) is at `path` (in its pinned folder, if pinned)."""
    return _lstat(path) is not None


def is_file(path: str) -> bool:
    """Whether `path` is a regular file (not a link, folder, FIFO or device)."""
    found = _lstat(path)
    return found is not None and stat.S_ISREG(found.st_mode)


def _what(mode: int) -> str:
    return ("a symbolic link" if stat.S_ISLNK(mode) else "a folder" if stat.S_ISDIR(mode) else
            "a FIFO" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else "a device")


def listdir(folder: str) -> list[str]:
    """The names in `folder` (through its descriptor, if pinned; [] for a folder that is not there)."""
    fd = _PINNED.get(os.path.abspath(folder))
    if fd is None and not os.path.isdir(folder):
        return []
    return os.listdir(folder if fd is None else fd)


def remove(path: str) -> None:
    """Removes the file `path` (in its pinned folder, if pinned); never a folder."""
    fd, name = _at(path)
    os.unlink(name, dir_fd=fd)


def open_file(path: str, max_bytes: int | None = None) -> IO[bytes]:
    """`path` opened for reading: only a regular file, never through a link, never blocking (a FIFO named like a
    result is refused at once); raises `NotAFile` for anything else, ValueError for one larger than `max_bytes`,
    OSError as `open` does."""
    fd, name = _at(path)
    try:
        handle = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, dir_fd=fd)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise NotAFile(path, "a symbolic link") from None
        raise
    found = os.fstat(handle)
    if not stat.S_ISREG(found.st_mode):
        os.close(handle)
        raise NotAFile(path, _what(found.st_mode))
    if max_bytes is not None and found.st_size > max_bytes:
        os.close(handle)
        raise ValueError(f"it is {found.st_size} bytes, more than the {max_bytes} its reader allows")
    return os.fdopen(handle, "rb")


def read_bytes(path: str, max_bytes: int | None = None) -> bytes:
    """The contents of the regular file `path` (`open_file`)."""
    with open_file(path, max_bytes) as f:
        return f.read()


def write_atomically(path: str, data: bytes) -> None:
    """Writes `data` to a temporary file and renames it over `path`: a crash leaves the old file or the new one.

    In a folder with a manifest (`claim`), the file's name is recorded in it first, so that `--overwrite` knows
    every file mqd-jax wrote there, a file interrupted halfway included; a file already there that the manifest
    does not list (a user's) is refused with a ValueError, never replaced. In a pinned folder (`lock`) every step
    goes through the folder's descriptor.
    """
    _record(os.path.dirname(path) or ".", os.path.basename(path))
    fd, name = _at(path)
    found = _lstat(path)
    if found is not None and not stat.S_ISREG(found.st_mode):
        raise NotAFile(path, _what(found.st_mode))
    tmp = f"{name}.{secrets.token_hex(4)}{TMP_SUFFIX}"
    # O_EXCL | O_NOFOLLOW: a new file of our own, never one placed there; the umask sets its mode, as `open`'s.
    handle = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666, dir_fd=fd)
    try:
        with os.fdopen(handle, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, name, src_dir_fd=fd, dst_dir_fd=fd)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp, dir_fd=fd)
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
    if not (x is None or isinstance(x, (bool, int, float, str))):
        raise ValueError(f"{where or 'the value'} is a {type(x).__name__}, which JSON cannot hold")
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
    try:
        data = _as_read(dict(payload), infinite)
    except ValueError as e:
        raise ValueError(f"{path!r} cannot be written: {e}") from None
    if infinite:
        warnings.warn(f"{path}: {', '.join(sorted(infinite))} hold infinite values, written as the strings "
                      '"Infinity"/"-Infinity" (JSON has no number for them)', InfiniteValues, stacklevel=2)
    write_atomically(path, json.dumps({**data, CHECKSUM: _json_digest(data)}).encode())


def _depth(x: Any) -> int:
    """How deeply lists and dicts nest in `x` (a parsed JSON value), found without recursion."""
    deepest, todo = 0, [(x, 1)]
    while todo:
        x, level = todo.pop()
        if isinstance(x, (dict, list)):
            deepest = max(deepest, level)
            todo.extend((v, level + 1) for v in (x.values() if isinstance(x, dict) else x))
    return deepest


def read_json(path: str, repair: str) -> dict[str, Any]:
    """The dict `write_json` wrote to `path`, its checksum verified (and removed).

    Raises `Damaged` (naming the file, what is wrong and `repair`, the way to repair it) if the file cannot be read
    or parsed (NaN and Infinity literals are not JSON; nesting deeper than `MAX_DEPTH`), is not a dict, carries no
    checksum or does not match it.
    """
    try:
        data = json.loads(read_bytes(path, MAX_JSON), parse_constant=_not_json)
        if not (isinstance(data, dict) and isinstance(data.get(CHECKSUM), str)):
            raise Damaged(path, "carries no checksum (not written by mqd-jax 0.9.0 or later)", repair)
        if _depth(data) > MAX_DEPTH:
            raise Damaged(path, f"is nested more than {MAX_DEPTH} levels deep (mqd-jax writes no such file)", repair)
        digest = data.pop(CHECKSUM)
        sealed = _json_digest(data) == digest
    except RecursionError as e:  # in the parse or in the digest's encoding
        raise Damaged(path, "cannot be read (nested too deep)", repair) from e
    except Damaged:
        raise
    except (OSError, ValueError) as e:  # ValueError: JSONDecodeError and UnicodeDecodeError
        raise Damaged(path, f"cannot be read ({type(e).__name__}: {e})", repair) from e
    if not sealed:
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


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, budget: int) -> np.ndarray:
    """One array of an npz file, read only after its declared size and its npy header fit `budget` bytes, and
    never more bytes than the header declares (a member that inflates further is damaged)."""
    if info.file_size > budget:
        raise ValueError(f"its member {info.filename!r} declares {info.file_size} bytes, more than the {budget} "
                         "its config implies")
    with zf.open(info) as member:
        version = np.lib.format.read_magic(member)
        if version not in ((1, 0), (2, 0)):
            raise ValueError(f"its member {info.filename!r} has npy format {version}")
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
            np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read_header(member)
        if dtype.hasobject:
            raise ValueError(f"its member {info.filename!r} holds Python objects (never read)")
        nbytes = math.prod(shape) * dtype.itemsize
        if nbytes > min(budget, info.file_size):
            raise ValueError(f"its member {info.filename!r} declares shape {shape} of {dtype} ({nbytes} bytes), more "
                             f"than its config implies ({budget}) or its zip entry holds ({info.file_size})")
        data = member.read(nbytes)
        if len(data) != nbytes or member.read(1):
            raise ValueError(f"its member {info.filename!r} does not hold the {nbytes} bytes its header declares")
    array = np.frombuffer(data, dtype).reshape(shape, order="F" if fortran else "C")
    return array.copy()


def read_npz(path: str, repair: str, max_bytes: int = 2**31) -> dict[str, np.ndarray]:
    """The arrays `write_npz` wrote to `path`, their checksum verified (and removed); raises `Damaged` like
    `read_json`, and for a file whose arrays (declared sizes, npy headers, inflated bytes) exceed `max_bytes`, what
    the caller's config implies: nothing past that is read or allocated."""
    try:
        with open_file(path) as f, zipfile.ZipFile(f) as zf:
            arrays, budget = {}, max_bytes
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    raise ValueError(f"its member {info.filename!r} is not an array")
                arrays[info.filename[:-4]] = array = _read_member(zf, info, budget)
                budget -= array.nbytes
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as e:
        raise Damaged(path, f"cannot be read ({type(e).__name__}: {e})", repair) from e
    digest = arrays.pop(CHECKSUM, None)
    if digest is None or digest.shape != () or digest.dtype.kind != "U":
        raise Damaged(path, "carries no checksum (not written by mqd-jax 0.9.0 or later)", repair)
    if _npz_digest(arrays) != str(digest):
        raise Damaged(path, "does not match its checksum: it was altered or damaged", repair)
    return arrays


def _check_path(folder: str) -> None:
    """Refuses (ValueError) a folder path the system cannot hold (a name longer than its file system allows, or
    a path longer than PATH_MAX) before any of its folders is made."""
    parts = [p for p in os.path.abspath(folder).split(os.sep) if p]
    existing = os.sep
    for part in parts:  # the deepest folder that exists: its file system's limits
        if not os.path.isdir(os.path.join(existing, part)):
            break
        existing = os.path.join(existing, part)
    try:
        longest, total = os.pathconf(existing, "PC_NAME_MAX"), os.pathconf(existing, "PC_PATH_MAX")
    except (OSError, ValueError):
        return
    long = [p for p in parts if len(os.fsencode(p)) > longest]
    if long:
        raise ValueError(f"{folder!r} is invalid: its part {long[0][:40]!r}... is {len(os.fsencode(long[0]))} bytes, "
                         f"more than the {longest} a name may have here; give a shorter --out")
    if len(os.fsencode(os.path.abspath(folder))) + len(MANIFEST) + 40 > total:
        raise ValueError(f"{folder!r} is invalid: the path is longer than the {total} bytes a path may have here "
                         "(with its files' names); give a shorter --out")


def _make_folder(folder: str, create: bool) -> list[str]:
    """Makes `folder` (if `create`) after checking its path; returns the folders it made, outermost first."""
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise ValueError(f"{folder!r} is a file, not a folder: give another --out")
    if os.path.islink(folder) and not os.path.exists(folder):
        raise ValueError(f"{folder!r} is a symbolic link to nothing: give another --out, or make the folder it "
                         "points to")
    if not create and not os.path.isdir(folder):
        raise ValueError(f"{folder!r} does not exist: give a folder that `mqd sweep` wrote")
    _check_path(folder)
    made, path = [], os.path.abspath(folder)
    while not os.path.lexists(path):
        made.insert(0, path)
        path = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    return made


def _unclaim(folder: str, pin: int) -> None:
    """Removes the manifest of `folder` (pinned) if it lists no file the folder holds: what a command that failed
    or was interrupted before writing anything leaves of its claim."""
    with contextlib.suppress(ValueError, OSError):
        saved = _manifest(folder)
        if saved is not None and not written(folder, saved):
            os.unlink(MANIFEST, dir_fd=pin)


def _open_lock(folder: int, shown: str) -> int:
    """The lock file in the folder `folder` (a descriptor), opened (created if missing) and locked: never through a
    link, only a regular file of one name. Raises ValueError if another process holds it or the path is not such a
    file (`shown`: the lock's path, for messages)."""
    while True:
        try:
            fd = os.open(LOCK, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o644,
                         dir_fd=folder)
        except OSError as e:
            if e.errno != errno.ELOOP:
                raise
            raise ValueError(f"{shown!r} is a symbolic link, not mqd-jax's lock file (mqd-jax never follows it): "
                             "remove it") from None
        opened = os.fstat(fd)
        if not stat.S_ISREG(opened.st_mode) or opened.st_nlink != 1:
            os.close(fd)
            what = "a file with other hard links" if stat.S_ISREG(opened.st_mode) else "not a regular file"
            raise ValueError(f"{shown!r} is not mqd-jax's lock file ({what}): remove it")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise ValueError(f"{os.path.dirname(shown)!r} is being written by another mqd process (pid {holder}): "
                             "wait for it to finish, or write to another folder") from None
        try:  # a holder that finished removed the file we opened: lock the one the folder holds now
            now = os.stat(LOCK, dir_fd=folder, follow_symlinks=False)
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
    made = re.compile(r"(.+)\.[A-Za-z0-9_]{8}" + re.escape(TMP_SUFFIX))  # write_atomically's (and mkstemp's) names
    return sorted(os.path.join(folder, n) for n in listdir(folder)
                  if (m := made.fullmatch(n)) and m.group(1) in ours and is_file(os.path.join(folder, n)))


def where_now(fd: int) -> str | None:
    """Where the folder open as `fd` sits now (Linux's /proc), or None where the system does not say."""
    try:
        return os.readlink(f"/proc/self/fd/{fd}")
    except OSError:
        return None


@contextlib.contextmanager
def lock(folder: str, create: bool = True) -> Iterator[list[str]]:
    """Holds `folder`'s write lock (creating the folder if `create`, else refusing a missing one) and pins it: until
    the lock is released, every file operation of this module on a path in `folder` goes through the descriptor
    opened here, so a folder moved or replaced meanwhile cannot redirect a write (see the module's docstring).
    Yields the leftover temporary files of killed writers it removed. The lock file is removed when the lock is
    released; if the folder no longer sits at its path then, a line on standard error says where it is.

    A command that fails or is interrupted (an exception leaves the block) before it has written a file leaves the
    folder as it found it: a manifest the block made that lists no file there is removed, and so are the folders
    `lock` made, if empty.

    Raises ValueError if another process holds it, if the folder is missing and not `create`, or if the lock
    file's path is anything but a regular file (a link is never followed).
    """
    made = _make_folder(folder, create)
    key = os.path.abspath(folder)
    if key in _PINNED:
        raise ValueError(f"{folder!r} is already locked by this process")
    pin = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        fd = _open_lock(pin, os.path.join(folder, LOCK))
    except BaseException:
        os.close(pin)
        raise
    _PINNED[key] = pin
    failed, claimed = False, lexists(os.path.join(folder, MANIFEST))
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        leftovers = _leftovers(folder)
        for leftover in leftovers:  # no other writer can be writing them: we hold the lock
            remove(leftover)
        yield leftovers
    except BaseException:
        failed = True
        raise
    finally:
        if failed and not claimed:
            _unclaim(folder, pin)
        del _PINNED[key]
        with contextlib.suppress(OSError):  # still ours (we hold its lock): nobody else can be using it
            os.unlink(LOCK, dir_fd=pin)
        os.close(fd)
        try:
            here = os.stat(folder)
        except OSError:
            here = None
        pinned = os.fstat(pin)
        if here is None or (here.st_dev, here.st_ino) != (pinned.st_dev, pinned.st_ino):
            now = where_now(pin)
            print(f"note: {folder!r} was moved or replaced while this command ran; everything it wrote is in the "
                  f"folder it started in, {'now at ' + repr(now) if now else 'which is no longer at that path'} "
                  f"({folder!r} now holds {'nothing' if here is None else 'another folder'}, left untouched)",
                  file=sys.stderr)
        elif failed:
            for path in reversed(made):  # only empty ones: rmdir removes nothing else
                with contextlib.suppress(OSError):
                    os.rmdir(path)
        os.close(pin)


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
        if not lexists(path):
            continue
        target, n = path + ".damaged", 1
        while lexists(target):
            n += 1
            target = f"{path}.damaged-{n}"
        (fd, name), (_, new) = _at(path), _at(target)
        os.rename(name, new, src_dir_fd=fd, dst_dir_fd=fd)
        moved.append(target)
    return moved


def _plain_name(name: Any) -> bool:
    """Whether `name` is a plain file name: a string naming a file directly in a folder (no path, no `..`)."""
    return (isinstance(name, str) and name not in ("", ".", "..") and "/" not in name and os.sep not in name
            and "\0" not in name and (os.altsep is None or os.altsep not in name))


def _manifest(folder: str) -> dict[str, Any] | None:
    """The manifest of `folder` (None if it has none); raises `Damaged` for a damaged one, and for one that names
    anything but plain file names of the folder's regular files (a path, `..`, a folder, a link or a FIFO);
    `NotAFile` where the manifest itself is not a regular file."""
    path = os.path.join(folder, MANIFEST)
    found = _lstat(path)
    if found is None:
        return None
    if not stat.S_ISREG(found.st_mode):
        raise NotAFile(path, _what(found.st_mode))
    repair = ("pass --overwrite to replace the folder's results (only files mqd-jax can prove it wrote are "
              "removed), or write to another folder")
    saved = read_json(path, repair)
    if not (isinstance(saved.get("identity"), dict) and isinstance(saved.get("written"), list)):
        raise Damaged(path, "is not an mqd-jax manifest", "remove it, or write to another folder")
    for name in saved["written"]:
        if not _plain_name(name) or name in (MANIFEST, LOCK):
            raise Damaged(path, f"lists {name!r}, which is not a plain file name of the folder", repair)
        found = _lstat(os.path.join(folder, name))
        if found is not None and not stat.S_ISREG(found.st_mode):
            raise Damaged(path, f"lists {name!r}, which is {_what(found.st_mode)} (mqd-jax writes only files)",
                          repair)
    return saved


def _record(folder: str, name: str) -> None:
    """Adds `name` to the files the manifest of `folder` lists as written by mqd-jax (if it has a manifest);
    refuses (ValueError) a file already there that the manifest does not list: it is not ours to replace."""
    if name in (MANIFEST, LOCK):
        return
    saved = _manifest(folder)
    if saved is not None and name not in saved["written"]:
        if lexists(os.path.join(folder, name)):
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


def identity(folder: str) -> dict[str, Any] | None:
    """What the manifest of `folder` says the folder holds (a run's config and seed); None without a sound one."""
    try:
        saved = _manifest(folder)
    except Damaged:
        return None
    return None if saved is None else saved["identity"]


def written(folder: str, saved: dict[str, Any] | None = None) -> list[str]:
    """The names of the files in `folder` that mqd-jax wrote there (its manifest's list, read unless `saved`
    gives it; [] without one)."""
    saved = _manifest(folder) if saved is None else saved
    return [] if saved is None else [n for n in saved["written"] if is_file(os.path.join(folder, n))]


def remove_written(folder: str, patterns: Sequence[str]) -> list[str]:
    """Removes the files of `folder` that match the glob `patterns` and that its manifest lists as written by
    mqd-jax (nothing in a folder without a manifest); returns their paths. A user's file is never removed."""
    removed = [os.path.join(folder, n) for n in written(folder) if any(fnmatch.fnmatchcase(n, p) for p in patterns)]
    for path in removed:
        remove(path)
    return removed


MARK = "<!-- mqd-jax: "  # the last line of every markdown file mqd-jax writes: its provenance, as JSON


def _png_text(data: bytes, key: bytes) -> str | None:
    """The tEXt entry `key` of the PNG `data` (None if it has none, or is not a PNG)."""
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        return None
    at = 8
    while at + 8 <= len(data):
        size, kind = int.from_bytes(data[at:at + 4], "big"), data[at + 4:at + 8]
        body = data[at + 8:at + 8 + size]
        if kind == b"tEXt" and body.partition(b"\0")[0] == key:
            return body.partition(b"\0")[2].decode("latin-1")
        if kind == b"IEND":
            return None
        at += 12 + size
    return None


def carries_provenance(path: str) -> bool:
    """Whether the regular file `path` is a results file of any mqd-jax version, proved by the provenance in it
    (for a folder without a sound manifest): JSON with a "provenance", an npz with "meta", a checkpoint, a PNG
    whose Description holds mqd-jax's provenance, markdown ending with its mark. A link, a FIFO or anything
    unreadable is not."""
    def provenanced(text: Any) -> bool:
        return isinstance(text, dict) and ("provenance" in text or any(
            isinstance(v, dict) and "provenance" in v for v in text.values()))

    try:
        if path.endswith(".npz"):
            with open_file(path) as f, zipfile.ZipFile(f) as zf:
                return "meta.npy" in zf.namelist()
        data = read_bytes(path, MAX_JSON)
        if path.endswith(".json"):
            return provenanced(json.loads(data))
        if path.endswith(".msgpack"):
            restored = serialization.msgpack_restore(data)
            return isinstance(restored, dict) and "format" in restored
        if path.endswith(".png"):
            return provenanced(json.loads(_png_text(data, b"Description") or "null"))
        if path.endswith(".md"):
            last = data.decode().rstrip("\n").rpartition("\n")[2]
            return last.startswith(MARK) and provenanced(json.loads(last[len(MARK):].removesuffix(" -->")))
    except Exception:  # unreadable, or not a regular file: not provably ours
        return False
    return False


def _matching(folder: str, patterns: Sequence[str]) -> list[str]:
    """The names in `folder` (files or not) that match the glob `patterns`."""
    return sorted(n for n in listdir(folder) if any(fnmatch.fnmatchcase(n, p) for p in patterns))


def claim(folder: str, kind: str, identity: Mapping[str, Any], patterns: Sequence[str], overwrite: bool,
          upgrade: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
          check: Callable[[str], None] | None = None, at_stake: str = "") -> list[str]:
    """Makes `folder` the results folder of `identity` (call while holding its lock); returns the files removed or
    set aside.

    `patterns` are the glob patterns of the files this kind of command writes. The
    folder may already hold results of the same kind and identity (a run is then
    written again, a sweep continued). Anything else of ours in it (other
    identity, other kind, results without a manifest, a damaged manifest) is
    refused with a ValueError naming what differs and what `overwrite` would
    delete (`at_stake` adds to that, e.g. a checkpoint's progress), unless
    `overwrite`: then those results are removed first: the files the manifest
    lists or, without one, the files matching `patterns` that carry mqd-jax's
    provenance (`carries_provenance`). A file that fails `check` (which raises
    ValueError for a damaged file) is set aside as `.damaged`, not removed. A
    user's file is never removed: anything named like `patterns` that mqd-jax
    cannot prove it wrote (a table without its mark, a link, a folder, a FIFO) is
    refused, even with `overwrite`, with the list. `upgrade` brings an identity
    saved by an earlier version to today's form before it is compared.
    """
    try:
        saved = _manifest(folder)
    except Damaged as e:
        if not overwrite:
            raise
        print(f"{e}\n--overwrite removes only the files mqd-jax can prove it wrote and writes a new manifest")
        saved = None
    named = _matching(folder, patterns)
    if saved is not None:
        ours = written(folder, saved)
    else:
        ours = [n for n in named if carries_provenance(os.path.join(folder, n))]
    foreign = [n if is_file(os.path.join(folder, n)) else f"{n} ({_what(_lstat(os.path.join(folder, n)).st_mode)})"
               for n in named if n not in ours and n != MANIFEST]
    if foreign:
        raise ValueError(f"{folder!r} refused: {', '.join(foreign)} {'is' if len(foreign) == 1 else 'are'} not "
                         "written by mqd-jax here (not in its manifest mqd.json, and not provably its results) but "
                         f"named like its results: move {'it' if len(foreign) == 1 else 'them'} away, or write to "
                         "another folder (mqd-jax never removes them)")
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
        raise ValueError(f"{folder!r} refused: {why}. Write to another folder, or pass --overwrite to replace "
                         f"them: it deletes {', '.join(ours)}{at_stake} (damaged files are set aside, never deleted)")
    removed = discard(folder, ours, check) if why is not None else []
    payload = {"kind": kind, "identity": dict(identity), "written": [] if why is not None else ours,
               "provenance": provenance()}
    write_json(os.path.join(folder, MANIFEST), payload)
    return removed


def discard(folder: str, names: Sequence[str], check: Callable[[str], None] | None = None) -> list[str]:
    """Removes these files of `folder` (names mqd-jax wrote), but sets aside (`set_aside`) each that fails `check`
    (damaged: kept as `.damaged`); returns what was removed and, for each set aside, its new path."""
    done = []
    for name in names:
        path = os.path.join(folder, name)
        try:
            if check is not None:
                check(path)
        except ValueError:
            done += set_aside([path])
            continue
        remove(path)
        done.append(path)
    return done
