"""The `mqd` console command: the command line (`cli.main`) under Ctrl-C handling from its first instruction.

It holds `interrupts.latched` before JAX is imported, so that Ctrl-C while Python imports JAX is one line too
(raised once the import is done: raised inside jaxlib's initialization, it aborts the process), and after Ctrl-C
it leaves at once (exit status 130), without the interpreter's shutdown, which can crash while XLA's threads
still hold a program being compiled. It imports nothing but the standard library and `interrupts` at first.
"""

from __future__ import annotations

import os
import sys

from mqd_jax.experiment import interrupts


def entry() -> None:
    """The `mqd` console command: `cli.main()` inside `latched`, JAX's import included; exits 130 at once after
    Ctrl-C (one line on standard error), as `main` exits otherwise."""
    with interrupts.latched():
        try:
            with interrupts.deferred():  # JAX's import, a second or more
                from mqd_jax.experiment import cli

            cli.main()
            return
        except SystemExit as e:
            if e.code != 130:
                raise
        except BaseException:  # before `main` could say where; KeyboardInterrupt, or the ImportError it becomes
            if not interrupts.pressed():  # in the initialization of a C extension
                raise
            print("\ninterrupted while starting; nothing was written", file=sys.stderr)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(130)
