"""What the command line prints: files removed or set aside, counts, and the commands it suggests, written so that
they run as printed when pasted into a POSIX shell: every word quoted, a flag's value joined to it with `=` (an
--out of `-r` is not taken for a flag), and a word with a newline or another control character in bash's `$'...'`
quoting, so that the hint stays on one line."""

from __future__ import annotations

import os
import shlex


def say_removed(paths: list[str], why: str) -> None:
    """Says which files were removed, and which set aside (`folders.discard`: damaged files, kept as `.damaged`)."""
    aside = [p for p in paths if ".damaged" in os.path.basename(p)]
    gone = [p for p in paths if p not in aside]
    if gone:
        print(f"{why}: removed {', '.join(os.path.basename(p) for p in gone)}")
    if aside:
        print(f"{why}: set aside (damaged, never deleted) as {', '.join(os.path.basename(p) for p in aside)}")


def count_of(n: int, noun: str, plural: str | None = None) -> str:
    """'1 skill', '3 skills' ('2 finished batches' with its `plural`)."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"


def word(text: str) -> str:
    """`text` as one shell word on one line."""
    if text.isprintable():
        return shlex.quote(text)
    escaped = "".join(c if c.isprintable() and c not in "'\\" else
                      "\\" + c if c in "'\\" else
                      f"\\x{ord(c):02x}" if ord(c) < 256 else f"\\u{ord(c):04x}" for c in text)
    return f"$'{escaped}'"


def command(*words: str | tuple[str, str]) -> str:
    """The command of `words`: a str is a word, a (flag, value) pair the word `flag=value`."""
    return " ".join(f"{w[0]}={word(w[1])}" if isinstance(w, tuple) else word(w) for w in words)
