"""Results folders: one writer at a time, one config per folder, files written whole.

* `lock(folder)`: held while a command writes a folder. A second writer is
  refused with a ValueError; the kernel releases the lock when its process ends,
  however it ends (`flock`), so a killed run leaves no stale lock.
* `claim(folder, kind, identity, files, overwrite)`: a folder records in
  `mqd.json` what wrote it (`kind`: "run" or "sweep", and the identity: config
  and seed) and the provenance. Writing another identity into it is refused
  with the differing fields named, unless `overwrite`, which first removes the
  earlier results.
* `write_atomically(path, data)`: a temporary file renamed over `path`, so a
  crash leaves the old file or the new one; leftovers of killed writers are
  removed when the folder is next locked.
"""

from __future__ import annotations

import contextlib
import fcntl
import glob
import io
import json
import os
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from mqd_jax.provenance import provenance

MANIFEST = "mqd.json"
LOCK = ".mqd.lock"
TMP_SUFFIX = ".mqdtmp"
_UMASK = os.umask(0o022)
os.umask(_UMASK)  # read, then restored: the process's umask is unchanged


def write_atomically(path: str, data: bytes) -> None:
    """Writes `data` to a temporary file and renames it over `path`: a crash leaves the old file or the new one."""
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


def write_npz(path: str, **arrays: np.ndarray) -> None:
    """Writes `arrays` as a compressed `.npz` file at `path`, atomically (`write_atomically`)."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    write_atomically(path, buffer.getvalue())


def _make_folder(folder: str) -> None:
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise ValueError(f"{folder!r} is a file, not a folder: give another --out")
    os.makedirs(folder, exist_ok=True)


@contextlib.contextmanager
def lock(folder: str) -> Iterator[list[str]]:
    """Holds `folder`'s write lock (creating the folder); yields the leftover temporary files it removed.

    Raises ValueError if another process holds it.
    """
    _make_folder(folder)
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


def read_json(path: str) -> Any:
    """The JSON in `path`; a ValueError naming the file if it cannot be read or parsed."""
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError) as e:
        raise ValueError(f"cannot read {path!r}: {e}") from e


def _existing(folder: str, files: Sequence[str]) -> list[str]:
    """The paths in `folder` that match the patterns `files`."""
    return sorted({p for pattern in files for p in glob.glob(os.path.join(glob.escape(folder), pattern))})


def claim(folder: str, kind: str, identity: Mapping[str, Any], files: Sequence[str], overwrite: bool) -> list[str]:
    """Makes `folder` the results folder of `identity` (call while holding its lock); returns the files removed.

    `files` are the glob patterns of the results this kind of command writes. The
    folder may already hold results of the same kind and identity (a run is then
    written again, a sweep continued). Anything else of ours in it (other
    identity, other kind, or results without a manifest) is refused with a
    ValueError naming what differs, unless `overwrite`: then those results are
    removed first.
    """
    path = os.path.join(folder, MANIFEST)
    saved = read_json(path) if os.path.exists(path) else None
    if saved is not None and not (isinstance(saved, dict) and isinstance(saved.get("identity"), dict)):
        raise ValueError(f"{path!r} is damaged (not an mqd-jax manifest): remove it, or write to another folder")
    ours = _existing(folder, [*files, *(saved or {}).get("files", [])])
    if saved is not None and saved.get("kind") == kind and saved.get("identity") == dict(identity):
        return []
    if not ours:  # nothing to lose (a folder of ours whose run stopped before writing anything, or a new one)
        why = None
    elif saved is None:
        why = f"it holds results without a manifest ({os.path.basename(ours[0])}, ...; from an older mqd-jax?)"
    elif saved.get("kind") != kind:
        why = f"it holds the results of `mqd {saved.get('kind')}`"
    else:
        flat = lambda d: {**{k: v for k, v in d.items() if k != "config"}, **d.get("config", {})}  # noqa: E731
        why = f"it holds results of another run ({differences(flat(saved['identity']), flat(identity))})"
    removed: list[str] = []
    if why is not None:
        if not overwrite:
            raise ValueError(f"{folder!r} refused: {why}. Pass --overwrite to replace them, or write to another "
                             "folder")
        removed = ours
        for p in removed:
            os.remove(p)
    payload = {"kind": kind, "identity": dict(identity), "files": list(files), "provenance": provenance()}
    write_atomically(path, json.dumps(payload, indent=1).encode())
    return removed
