"""Results folders: one writer at a time, one config per folder, every file written whole and recorded.

* `lock(folder)`: held while a command writes a folder. A second writer is
  refused with a ValueError; the kernel releases the lock when its process ends,
  however it ends (`flock`), so a killed run leaves no stale lock, and a process
  that ends normally removes the lock file. The lock file is never followed: a
  symbolic link, a file with other hard links or anything but a regular file in
  its place is refused, so taking the lock cannot write anywhere else. The lock
  pins the folder (`files.pin`): a folder renamed or replaced under a running
  command (`mv R R.orig; mkdir R`, or a link swapped in) cannot redirect a single
  byte: the command finishes in the folder it started in, and says where that
  folder now is when it no longer sits at its path.
* `claim(folder, kind, identity, patterns, overwrite)`: a folder records in its
  manifest (`mqd_jax.experiment.manifest`) what wrote it. Writing another
  identity into it is refused with the differing fields named, unless
  `overwrite`, which first removes the files the manifest lists (those that fail
  their checks, `check`, are set aside as `.damaged`, never deleted), and nothing
  else: a user's own files in the folder are never removed. A folder without a
  sound manifest loses only files mqd-jax can prove it wrote (JSON, npz, msgpack
  and PNG files carrying its provenance); anything else named like a result (a
  table, a link, a folder, a FIFO) is refused with the list, even with
  `overwrite`.
* `write_atomically(path, data)`, `write_json`, `write_npz`: the file's name is
  recorded in the folder's manifest, then the file written whole
  (`mqd_jax.experiment.files`); a file already there that the manifest does not
  list is refused, never replaced. Leftovers of killed writers (the temporary
  files of names the manifest lists) are removed when the folder is next locked.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import fnmatch
import os
import stat
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from mqd_jax.experiment import files, manifest
from mqd_jax.experiment.files import Damaged
from mqd_jax.experiment.manifest import LOCK, MANIFEST
from mqd_jax.experiment.provenance import provenance


def write_atomically(path: str, data: bytes) -> None:
    """Writes `data` to `path` whole (`files.write`). In a folder with a manifest (`claim`), the file's name is
    recorded in it first, so that `--overwrite` knows every file mqd-jax wrote there, a file interrupted halfway
    included; a file already there that the manifest does not list (a user's) is refused with a ValueError, never
    replaced. In a pinned folder (`lock`) every step goes through the folder's descriptor."""
    manifest.record(os.path.dirname(path) or ".", os.path.basename(path))
    files.write(path, data)


def write_json(path: str, payload: Mapping[str, Any]) -> None:
    """Writes the dict `payload` as strict JSON with its checksum (`files.json_bytes`), atomically and recorded."""
    write_atomically(path, files.json_bytes(path, payload))


def write_npz(path: str, **arrays: np.ndarray) -> None:
    """Writes `arrays` as a compressed `.npz` file with their checksum (`files.npz_bytes`), atomically and
    recorded."""
    write_atomically(path, files.npz_bytes(path, **arrays))


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
    if files.is_pinned(folder):
        raise ValueError(f"{folder!r} is already locked by this process")
    pin = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        fd = _open_lock(pin, os.path.join(folder, LOCK))
    except BaseException:
        os.close(pin)
        raise
    files.pin(folder, pin)
    failed, claimed = False, files.lexists(os.path.join(folder, MANIFEST))
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        leftovers = manifest.leftovers(folder)
        for leftover in leftovers:  # no other writer can be writing them: we hold the lock
            files.remove(leftover)
        yield leftovers
    except BaseException:
        failed = True
        raise
    finally:
        if failed and not claimed:
            manifest.unclaim(folder)
        files.unpin(folder)
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


def _matching(folder: str, patterns: Sequence[str]) -> list[str]:
    """The names in `folder` (files or not) that match the glob `patterns`."""
    return sorted(n for n in files.listdir(folder) if any(fnmatch.fnmatchcase(n, p) for p in patterns))


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
        saved = manifest.read(folder)
    except Damaged as e:
        if not overwrite:
            raise
        print(f"{e}\n--overwrite removes only the files mqd-jax can prove it wrote and writes a new manifest")
        saved = None
    named = _matching(folder, patterns)
    if saved is not None:
        ours = manifest.written(folder, saved)
    else:
        ours = [n for n in named if manifest.carries_provenance(os.path.join(folder, n))]
    foreign = [n if files.is_file(path := os.path.join(folder, n)) else
               f"{n} ({files.what_is(files.status(path).st_mode)})" for n in named if n not in ours and n != MANIFEST]
    if foreign:
        raise ValueError(f"{folder!r} refused: {', '.join(foreign)} {'is' if len(foreign) == 1 else 'are'} not "
                         "written by mqd-jax here (not in its manifest mqd.json, and not provably its results) but "
                         f"named like its results: move {'it' if len(foreign) == 1 else 'them'} away, or write to "
                         "another folder (mqd-jax never removes them)")
    if saved is not None and upgrade is not None:
        saved["identity"] = upgrade(saved["identity"])
    same = saved is not None and files.as_read(saved.get("identity")) == files.as_read(dict(identity))
    if same and saved.get("kind") == kind:
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
    manifest.write(folder, payload)
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
            done += files.set_aside([path])
            continue
        files.remove(path)
        done.append(path)
    return done

