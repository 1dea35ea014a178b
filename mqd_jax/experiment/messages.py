"""What the command line prints of its work: files removed or set aside, counts."""

from __future__ import annotations

import os


def say_removed(paths: list[str], why: str) -> None:
    """Says which files were removed, and which set aside (`folders.discard`: damaged files, kept as `.damaged`)."""
    aside = [p for p in paths if ".damaged" in os.path.basename(p)]
    gone = [p for p in paths if p not in aside]
    if gone:
        print(f"{why}: removed {', '.join(os.path.basename(p) for p in gone)}")
    if aside:
        print(f"{why}: set aside (damaged, never deleted) as {', '.join(os.path.basename(p) for p in aside)}")


def count_of(n: int, noun: str) -> str:
    """'1 skill', '3 skills'."""
    return f"{n} {noun}{'' if n == 1 else 's'}"

