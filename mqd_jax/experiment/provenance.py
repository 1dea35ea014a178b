"""Where a result came from: package versions, the project's git revision, the machine.

Every results file (`mqd run`'s and `mqd sweep`'s JSON, npz and checkpoints)
records `provenance()` next to its config and key, so a result can be traced
to the code that made it.
"""

from __future__ import annotations

import functools
import importlib.metadata
import os
import platform
import subprocess
import sys

import jax

from mqd_jax.version import __version__

PACKAGES = ("mqd-jax", "jax", "jaxlib", "flax", "optax", "chex", "numpy", "mujoco", "mujoco-mjx")


def machine() -> str:
    """The machine figures were measured on, e.g. 'x86_64 (AMD EPYC with AVX-512 and VP2INTERSECT), 2 CPU cores,
    jax 0.10.2 on cpu (cpu) x 1': its CPU named (`cpu_model`), since one model name covers processors whose
    timing ratios differ by half (docs/results.md, "A generation parallel in its population")."""
    cpu = cpu_model()
    arch = platform.machine() if cpu == platform.machine() else f"{platform.machine()} ({cpu})"
    return (f"{arch}, {os.cpu_count()} CPU cores, jax {jax.__version__} on {jax.default_backend()} "
            f"({jax.devices()[0].device_kind}) x {jax.device_count()}")


def cpu_model(cpuinfo: str = "/proc/cpuinfo") -> str:
    """The CPU's model name, whether it has AVX-512 and whether that has VP2INTERSECT, or without AVX-512 whether it
    has VAES (MuJoCo's physics and M-QD's model may round otherwise on another one: one name, "AMD EPYC", covers
    processors of several generations); where `cpuinfo` cannot be read or names no model, the platform's processor
    or architecture."""
    try:
        with open(cpuinfo) as f:
            lines = f.read().splitlines()
        name = next(line.split(":", 1)[1].strip() for line in lines if line.startswith("model name"))
        flags = next((line.split(":", 1)[1].split() for line in lines if line.startswith("flags")), [])
        if "avx512f" not in flags:
            return name + (" with VAES" if "vaes" in flags else "")
        return name + " with AVX-512" + (" and VP2INTERSECT" if "avx512_vp2intersect" in flags else "")
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def _version(package: str) -> str | None:
    if package == "mqd-jax":  # this code's own version, even where an older install's metadata lingers
        return __version__
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return None


@functools.cache
def git_revision() -> str | None:
    """The git commit of the checkout mqd_jax runs from ('+dirty' with uncommitted changes), or None."""
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        run = lambda *a: subprocess.run(["git", "-C", here, *a], capture_output=True, text=True,  # noqa: E731
                                        timeout=10, check=True).stdout.strip()
        commit = run("rev-parse", "HEAD")
        return commit + ("+dirty" if run("status", "--porcelain", "--untracked-files=no") else "")
    except (OSError, subprocess.SubprocessError):
        return None


def provenance() -> dict[str, object]:
    """{"versions": {package: version}, "git": revision or None, "python": version, "machine": ...}."""
    return {"versions": {p: _version(p) for p in PACKAGES}, "git": git_revision(),
            "python": sys.version.split()[0], "machine": machine()}
