"""A run's traced parameters: the engine's `t_dist` and the emitter's own.

`Params` is a pytree of float32 arrays, so one compiled run can be `jax.vmap`-ed
over any of them (the way evosax separates `params` from its static settings).
The engine reads `t_dist`; `emitter` is whatever `Emitter.default_params()`
returns, a nested pytree for a composition (`ModelEmitter`'s holds its inner
emitter's and its acquisition rule's), and each component checks its own part
(`Emitter.check_params`). A component is handed the run's `Params` with `emitter`
set to its own part: it reads `params.t_dist` and `params.emitter.<its names>`.
"""

from __future__ import annotations

from typing import Any

import jax

from mqd_jax.core import pytree


@pytree.dataclass
class Params:
    """Traced parameters of a run.

    Attributes:
      t_dist: float32 scalar (or [R] in a sweep): the insertion distance threshold and coverage ball radius.
      emitter: the emitter's traced parameters (`Emitter.default_params()`; () for one without).
    """

    t_dist: jax.Array
    emitter: Any = ()

    def part(self, emitter: Any) -> Params:
        """These params with `emitter` as the emitter's part: what a wrapper hands a component it holds."""
        return self.replace(emitter=emitter)


def params_of(part: Any) -> Any:
    """A part's traced parameters (an acquisition rule's, a surrogate's): its `default_params()`, or () for a part
    without."""
    default = getattr(part, "default_params", None)
    return () if default is None else default()


def check_params_of(part: Any, params: Any) -> None:
    """A part's `check_params(params)`, where it has one."""
    check = getattr(part, "check_params", None)
    if check is not None:
        check(params)
