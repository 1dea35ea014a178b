"""Ctrl-C that always stops a command, wherever it is pressed.

Python raises KeyboardInterrupt in whatever Python code runs when the signal is
handled. While XLA compiles (in C++) that is often a garbage-collection
callback of jaxlib's, or a finalizer: an exception raised there is printed as
"Exception ignored in ..." and lost, and the command runs on for hours.
`latched()` installs a SIGINT handler that also remembers the press, and
delivers it again a moment later where it came in such a callback; the chunk
loops (`checkpoint.run_chunks`, `sweep.run_batch`) call `check()` after
compiling and after every chunk, so a press that was lost still stops the
command there, before any further generation runs.

The `mqd` command (`mqd_jax.experiment.command.entry`) holds the latch from its first instruction; this module
imports nothing but the standard library (nor does `import mqd_jax`), for that reason.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from types import FrameType

_PRESSED = threading.Event()
# Python code in which a raised KeyboardInterrupt is lost ("Exception ignored in ..."): the press is only
# remembered there, and `check` raises it.
_SWALLOWING = ("_xla_gc_callback", "__del__")
_AGAIN_S = 0.05  # when a press that came in one of them is delivered again
_DEFERRED: list[bool] = []  # inside `deferred`: presses are only remembered


def _pressed(signum: int, frame: FrameType | None) -> None:
    _PRESSED.set()
    if _DEFERRED:
        return
    if frame is not None and frame.f_code.co_name in _SWALLOWING:  # the signal again, once the callback is done
        threading.Timer(_AGAIN_S, signal.raise_signal, (signum,)).start()
        return
    raise KeyboardInterrupt


@contextlib.contextmanager
def latched() -> Iterator[None]:
    """SIGINT raises KeyboardInterrupt as usual and is remembered for `check` while the block runs (only in the
    main thread, where Python handles signals; elsewhere the block runs as it is). A press left from an earlier
    block is forgotten on entry; a block inside another keeps the outer one's."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is _pressed:
        yield  # another thread, or inside another `latched` block (`entry`'s), whose press is kept
        return
    _PRESSED.clear()
    previous = signal.signal(signal.SIGINT, _pressed)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _PRESSED.clear()


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Inside `latched`: a press is only remembered while the block runs, and raised when it ends. For imports of
    C extensions (jaxlib), where a KeyboardInterrupt raised in Python code that C++ called aborts the process."""
    _DEFERRED.append(True)
    try:
        yield
    finally:
        _DEFERRED.pop()
    check()


def pressed() -> bool:
    """Whether Ctrl-C was pressed inside `latched`: then an error that follows is its consequence (an extension
    being initialized turns KeyboardInterrupt into ImportError)."""
    return _PRESSED.is_set()


def check() -> None:
    """Raises KeyboardInterrupt if Ctrl-C was pressed inside `latched` (even where its KeyboardInterrupt was
    lost); does nothing otherwise, and outside `latched`."""
    if pressed():
        raise KeyboardInterrupt

