"""What the experiment scripts share: the machine line of a report, and writing a markdown report."""

from __future__ import annotations

import os
import platform

import jax


def machine() -> str:
    """The machine a figure was measured on, e.g. 'x86_64, 2 CPU cores, jax 0.10.2 on cpu (cpu)'."""
    return (f"{platform.machine()}, {os.cpu_count()} CPU cores, jax {jax.__version__} on {jax.default_backend()} "
            f"({jax.devices()[0].device_kind})")


def write(lines: list[str], path: str) -> None:
    """Prints a markdown report and writes it to `path` (creating its folder)."""
    table = "\n".join(lines)
    print(table)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(path, "w") as f:
        f.write(table + "\n")
