"""Results files, one at a time: only regular files, never through a link, written whole, checksummed, read
within bounds.

* Pinned folders: while a folder is pinned (`pin`, by `folders.lock`), every read, write, rename and removal of
  a file of that folder (`os.path.join(folder, name)` given to any function here) goes relative to its directory
  descriptor, never through the path again, so a folder renamed or replaced under a running command cannot
  redirect a single byte.
* Only regular files: every open is non-blocking and never follows a link, so a FIFO, a device or a link named
  like a result is refused, naming it (`NotAFile`), instead of hanging a command.
* `write(path, data)`: a temporary file renamed over `path`, so a crash leaves the old file or the new one (a
  results folder's writes go through `folders.write_atomically`, which records the name in its manifest first).
* `json_bytes` / `read_json`, `npz_bytes` / `read_npz`: every JSON and npz file the library writes carries a
  SHA-256 checksum of its contents (JSON: the key "sha256"; npz: the array "sha256"), verified on every read. A
  file that cannot be read, has no checksum or does not match it raises `Damaged` (a ValueError) naming the file,
  what is wrong and how to repair it; so does a JSON file with NaN or Infinity literals (not JSON) or nested
  deeper than `MAX_DEPTH`. Infinite values are written as the strings "Infinity" and "-Infinity" (JSON has no
  number for them), with a warning naming the key that holds them; a value JSON cannot hold (a complex number)
  is refused naming its key. Reads are bounded: `read_npz` checks every member's declared and inflated size and
  its npy header against the bytes the caller's config implies (`max_bytes`) before reading it, and a JSON file
  larger than `MAX_JSON` is refused unread. The checksum guards against accidents (a truncated or altered file),
  not against a forger, who can compute a new one: what a file's contents must satisfy is checked by its reader.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import io
import json
import math
import os
import secrets
import stat
import warnings
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from typing import IO, Any

import numpy as np

TMP_SUFFIX = ".mqdtmp"
CHECKSUM = "sha256"  # the key (JSON) or array (npz) that holds a file's checksum
MAX_JSON = 2**30  # the largest JSON file read (bytes): a sweep of 25 seeds x 10,000 generations is under 200 MB
MAX_DEPTH = 64  # the deepest nesting of lists and dicts read from a JSON file (mqd-jax's nest a few levels)
NPZ_SLACK = 2**24  # bytes an npz may hold beyond the arrays its config implies (its `meta` text)

# Folders pinned by `folders.lock`: absolute path as given -> the descriptor every file operation in it goes through.
_PINNED: dict[str, int] = {}


def pin(folder: str, fd: int) -> None:
    """Pins `folder` to the directory descriptor `fd` (see the module's docstring); ValueError if it is pinned."""
    key = os.path.abspath(folder)
    if key in _PINNED:
        raise ValueError(f"{folder!r} is already locked by this process")
    _PINNED[key] = fd


def unpin(folder: str) -> None:
    """Ends `pin`: paths in `folder` go through the path again."""
    del _PINNED[os.path.abspath(folder)]


def is_pinned(folder: str) -> bool:
    """Whether `folder` is pinned (`pin`)."""
    return os.path.abspath(folder) in _PINNED


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
    """Makes `folder` (and its parents) unless it is pinned: a pinned folder is there, wherever it sits."""
    if os.path.abspath(folder) not in _PINNED:
        os.makedirs(folder, exist_ok=True)


def status(path: str) -> os.stat_result | None:
    """The path's own status (a link's, not its target's); None if nothing is there."""
    fd, name = _at(path)
    try:
        return os.stat(name, dir_fd=fd, follow_symlinks=False)
    except FileNotFoundError:
        return None


def lexists(path: str) -> bool:
    """Whether anything (a file, a link, a folder ...) is at `path` (in its pinned folder, if pinned)."""
    return status(path) is not None


def is_file(path: str) -> bool:
    """Whether `path` is a regular file (not a link, folder, FIFO or device)."""
    found = status(path)
    return found is not None and stat.S_ISREG(found.st_mode)


def what_is(mode: int) -> str:
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
        raise NotAFile(path, what_is(found.st_mode))
    if max_bytes is not None and found.st_size > max_bytes:
        os.close(handle)
        raise ValueError(f"it is {found.st_size} bytes, more than the {max_bytes} its reader allows")
    return os.fdopen(handle, "rb")


def read_bytes(path: str, max_bytes: int | None = None) -> bytes:
    """The contents of the regular file `path` (`open_file`)."""
    with open_file(path, max_bytes) as f:
        return f.read()


def write(path: str, data: bytes) -> None:
    """Writes `data` to a temporary file and renames it over `path`: a crash leaves the old file or the new one.
    Never through a link, never over anything but a regular file (`NotAFile`); in a pinned folder every step goes
    through the folder's descriptor."""
    fd, name = _at(path)
    found = status(path)
    if found is not None and not stat.S_ISREG(found.st_mode):
        raise NotAFile(path, what_is(found.st_mode))
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


def as_read(payload: Any, infinite: set[str] | None = None) -> Any:
    """`payload` as JSON reads it back (tuples as lists, NaN as null, +-inf as strings, keys as strings)."""
    return json.loads(json.dumps(_strict(payload, infinite=infinite), allow_nan=False))


def json_digest(payload: Any) -> str:
    """The SHA-256 of `payload` as canonical JSON (sorted keys, no spaces), as read back from a file."""
    return hashlib.sha256(json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()
                          ).hexdigest()


class InfiniteValues(UserWarning):
    """A results file holds infinite values (written as the strings "Infinity" and "-Infinity")."""


def _not_json(literal: str) -> Any:
    """`json.loads`' parse_constant: NaN, Infinity and -Infinity are not JSON (mqd-jax writes none of them)."""
    raise ValueError(f"the literal {literal} is not JSON")


def json_bytes(path: str, payload: Mapping[str, Any]) -> bytes:
    """The dict `payload` as strict JSON (NaN as null) with its checksum (key "sha256"), the file `path`'s bytes;
    ValueError, naming the file and the key, for a value JSON cannot hold."""
    if CHECKSUM in payload:
        raise ValueError(f"{path!r}: the key {CHECKSUM!r} is the file's checksum; give the payload another key")
    infinite: set[str] = set()
    try:
        data = as_read(dict(payload), infinite)
    except ValueError as e:
        raise ValueError(f"{path!r} cannot be written: {e}") from None
    if infinite:
        warnings.warn(f"{path}: {', '.join(sorted(infinite))} hold infinite values, written as the strings "
                      '"Infinity"/"-Infinity" (JSON has no number for them)', InfiniteValues, stacklevel=3)
    return json.dumps({**data, CHECKSUM: json_digest(data)}).encode()


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
        sealed = json_digest(data) == digest
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


def npz_bytes(path: str, **arrays: np.ndarray) -> bytes:
    """`arrays` as a compressed `.npz` file with their checksum (array "sha256"): the file `path`'s bytes."""
    if CHECKSUM in arrays:
        raise ValueError(f"{path!r}: the array {CHECKSUM!r} is the file's checksum; give the array another name")
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays, **{CHECKSUM: np.asarray(_npz_digest(arrays))})
    return buffer.getvalue()


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
