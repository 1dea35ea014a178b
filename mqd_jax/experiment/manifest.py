"""A results folder's manifest, `mqd.json`: what wrote the folder (`kind`: "run" or "sweep", and its identity:
config and seed), the provenance, what a command planned to write, and the name of every file mqd-jax has written
in it (`record`, called by `folders.write_atomically` before the file is written).

A manifest entry must be a plain file name of a regular file directly in the folder (no path, no `..`, no link):
anything else makes the manifest damaged, so no command ever removes or writes a file outside its folder. In a
folder with a manifest, a file the manifest does not list (a user's) is never replaced nor removed. In a folder
without a sound one, a file is mqd-jax's only if it carries its provenance (`carries_provenance`).
"""

from __future__ import annotations

import fnmatch
import json
import os
import re
import stat
import zipfile
from collections.abc import Mapping, Sequence
from typing import Any

from flax import serialization

from mqd_jax.experiment import files
from mqd_jax.experiment.files import Damaged, NotAFile

MANIFEST = "mqd.json"
LOCK = ".mqd.lock"  # the folder's lock (`folders.lock`): never listed, never a result


def write(folder: str, payload: Mapping[str, Any]) -> None:
    """Writes `payload` as the manifest of `folder` (a checksummed JSON file, atomically)."""
    path = os.path.join(folder, MANIFEST)
    files.write(path, files.json_bytes(path, payload))


def _plain_name(name: Any) -> bool:
    """Whether `name` is a plain file name: a string naming a file directly in a folder (no path, no `..`)."""
    return (isinstance(name, str) and name not in ("", ".", "..") and "/" not in name and os.sep not in name
            and "\0" not in name and (os.altsep is None or os.altsep not in name))


def read(folder: str) -> dict[str, Any] | None:
    """The manifest of `folder` (None if it has none); raises `Damaged` for a damaged one, and for one that names
    anything but plain file names of the folder's regular files (a path, `..`, a folder, a link or a FIFO);
    `NotAFile` where the manifest itself is not a regular file."""
    path = os.path.join(folder, MANIFEST)
    found = files.status(path)
    if found is None:
        return None
    if not stat.S_ISREG(found.st_mode):
        raise NotAFile(path, files.what_is(found.st_mode))
    repair = ("pass --overwrite to replace the folder's results (only files mqd-jax can prove it wrote are "
              "removed), or write to another folder")
    saved = files.read_json(path, repair)
    if not (isinstance(saved.get("identity"), dict) and isinstance(saved.get("written"), list)):
        raise Damaged(path, "is not an mqd-jax manifest", "remove it, or write to another folder")
    for name in saved["written"]:
        if not _plain_name(name) or name in (MANIFEST, LOCK):
            raise Damaged(path, f"lists {name!r}, which is not a plain file name of the folder", repair)
        found = files.status(os.path.join(folder, name))
        if found is not None and not stat.S_ISREG(found.st_mode):
            raise Damaged(path, f"lists {name!r}, which is {files.what_is(found.st_mode)} (mqd-jax writes only files)",
                          repair)
    return saved


def record(folder: str, name: str) -> None:
    """Adds `name` to the files the manifest of `folder` lists as written by mqd-jax (if it has a manifest);
    refuses (ValueError) a file already there that the manifest does not list: it is not ours to replace."""
    if name in (MANIFEST, LOCK):
        return
    saved = read(folder)
    if saved is not None and name not in saved["written"]:
        if files.lexists(os.path.join(folder, name)):
            raise ValueError(f"{os.path.join(folder, name)!r} is not written by mqd-jax here (not in its manifest "
                             f"{MANIFEST}), so it is not replaced: move it away, or write to another folder")
        saved["written"].append(name)
        write(folder, saved)


def plan(folder: str, planned: Sequence[Mapping[str, Any]]) -> None:
    """Adds `planned` (what a command is about to write, e.g. a sweep's batches) to the manifest of `folder` (key
    "planned"; call holding its lock, after `claim`), so that what is missing after an interruption can be named."""
    saved = read(folder)
    if saved is None:
        raise ValueError(f"{folder!r} has no manifest: claim it first")
    entries = list(saved.get("planned", []))
    entries += [e for e in files.as_read(list(planned)) if e not in entries]
    if entries != saved.get("planned"):
        write(folder, {**saved, "planned": entries})


def planned(folder: str) -> list[dict[str, Any]]:
    """What the manifest of `folder` says was planned (`plan`); [] without a sound manifest."""
    try:
        saved = read(folder)
    except Damaged:
        return []
    entries = [] if saved is None else saved.get("planned", [])
    return [e for e in entries if isinstance(e, dict)] if isinstance(entries, list) else []


def kind(folder: str) -> str | None:
    """What wrote `folder`, as its manifest says ("run" or "sweep"); None without a sound manifest."""
    try:
        saved = read(folder)
    except Damaged:
        return None
    return None if saved is None else saved.get("kind")


def identity(folder: str) -> dict[str, Any] | None:
    """What the manifest of `folder` says the folder holds (a run's config and seed); None without a sound one."""
    try:
        saved = read(folder)
    except Damaged:
        return None
    return None if saved is None else saved["identity"]


def written(folder: str, saved: dict[str, Any] | None = None) -> list[str]:
    """The names of the files in `folder` that mqd-jax wrote there (its manifest's list, read unless `saved`
    gives it; [] without one)."""
    saved = read(folder) if saved is None else saved
    return [] if saved is None else [n for n in saved["written"] if files.is_file(os.path.join(folder, n))]


def remove_written(folder: str, patterns: Sequence[str]) -> list[str]:
    """Removes the files of `folder` that match the glob `patterns` and that its manifest lists as written by
    mqd-jax (nothing in a folder without a manifest); returns their paths. A user's file is never removed."""
    removed = [os.path.join(folder, n) for n in written(folder) if any(fnmatch.fnmatchcase(n, p) for p in patterns)]
    for path in removed:
        files.remove(path)
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
            with files.open_file(path) as f, zipfile.ZipFile(f) as zf:
                return "meta.npy" in zf.namelist()
        data = files.read_bytes(path, files.MAX_JSON)
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


def leftovers(folder: str) -> list[str]:
    """The temporary files that killed writers left in `folder`: those of the names its manifest lists (and of
    the manifest itself); [] for a folder without a sound manifest (nothing there is known to be ours)."""
    try:
        saved = read(folder)
    except Damaged:
        saved = None
    if saved is None:
        return []
    ours = {MANIFEST, *saved["written"]}
    made = re.compile(r"(.+)\.[A-Za-z0-9_]{8}" + re.escape(files.TMP_SUFFIX))  # files.write's (and mkstemp's) names
    return sorted(os.path.join(folder, n) for n in files.listdir(folder)
                  if (m := made.fullmatch(n)) and m.group(1) in ours and files.is_file(os.path.join(folder, n)))


def unclaim(folder: str) -> None:
    """Removes the manifest of `folder` if it lists no file the folder holds: what a command that failed or was
    interrupted before writing anything leaves of its claim (`folders.lock`)."""
    try:
        saved = read(folder)
    except (ValueError, OSError):
        return
    if saved is not None and not written(folder, saved):
        files.remove(os.path.join(folder, MANIFEST))
