"""The task protocol: what a task gives the QD engine.

A task is a bounded action box, a bounded behavior box of 1 to 8 dimensions
(plus the reachable part of it, for coverage), and a pure, vmappable rollout:

    evaluate(actions[B, n], key) -> (behaviors[B, d], qualities[B], valid[B])

`valid[b] = False` marks a failed rollout: it counts as an evaluation but is
never inserted. Subclass `Task` (a frozen dataclass) and implement `evaluate`;
override `reachable` if part of the behavior box cannot be reached, and
`quality_range` (a class attribute, default (0, 1)) if qualities lie elsewhere:
M-QD's model maps it to its tanh output range. A backend that can skip
rollouts (a host callback) overrides `evaluate_masked`. `layout` lists the
scene's parts (`Region`s) that figures draw under the behaviors.

`features(actions)` is how a task tells M-QD's model what is cheap to know: a
jittable function of the actions alone, without physics (forward kinematics of
a robot's path, where a point robot's straight path first meets a wall), whose
values the model takes as inputs beside the actions. The default has none.

`auxiliary` names what else a rollout observes on the way (whether and when
a pusher touched the object, where the object was part-way): a task that names
some implements `evaluate_with_auxiliary`, which returns them beside
`evaluate_masked`'s outputs, auxiliary [B, m] (one column per name, about
[-1, 1]); M-QD's model may learn them (`mqd_jax.surrogate.gate`). The default
names none.

A task also says which of the paper's settings apply to it (class attributes;
the framework knows no task by name): `table_ii_column` ("2d" or "robot", the
defaults `Config.paper` takes), `paper_seeds` (runs per algorithm in a sweep)
and `paper_coverage` (Table I's final coverage per preset, for comparison).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class Region:
    """A part of a task's scene in behavior coordinates (the first two), drawn under the behaviors in figures.

    Attributes:
      label: legend text ("obstacle", "table", ...).
      low, high: the corners of its bounding box.
      shape: "box", or "disk" (the disk inscribed in the box).
      filled: filled, or drawn as a dashed outline.
      colour: a matplotlib colour; None: grey.
    """

    label: str
    low: tuple[float, float]
    high: tuple[float, float]
    shape: str = "box"
    filled: bool = True
    colour: str | tuple[float, float, float] | None = None


@dataclasses.dataclass(frozen=True, eq=False)
class Task:
    """Base class of every task. Bounds are tuples so the task stays hashable.

    Attributes:
      action_low, action_high: per-dimension action bounds, length n.
      behavior_low, behavior_high: the behavior box, length d.
      quality_range: (low, high) of the qualities `evaluate` returns; a class
        attribute, fixed per task. M-QD's model normalizes qualities with it.
      auxiliary: names of the auxiliary outputs [B, m] `evaluate_with_auxiliary` returns
        (a class attribute; default none).
      table_ii_column: "2d" or "robot": the paper's Table II column of
        defaults that `Config.paper` gives this task.
      default_t_dist: the `t_dist` Table II's columns (`Config.paper`, `paper_2d`, `paper_robot`; the command
        line's presets) give this task when none is given, for a behavior space whose scale is not Table II's
        (None: Table II's 0.02); in behavior units.
      paper_seeds: runs per algorithm in the paper's experiments (`mqd sweep`'s default).
      paper_coverage: the paper's Table I, {preset: (mean, std) final coverage};
        empty for tasks the paper does not have.
      revision: raise it when what the task's rollouts give changes (its physics, behaviors or qualities): a
        checkpoint written at another revision is then refused, not continued with skills of the old task.
    """

    quality_range: ClassVar[tuple[float, float]] = (0.0, 1.0)
    auxiliary: ClassVar[tuple[str, ...]] = ()
    table_ii_column: ClassVar[str] = "2d"
    default_t_dist: ClassVar[float | None] = None
    paper_seeds: ClassVar[int] = 25
    paper_coverage: ClassVar[Mapping[str, tuple[float, float]]] = {}
    revision: ClassVar[int] = 0

    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    behavior_low: tuple[float, ...]
    behavior_high: tuple[float, ...]

    @property
    def action_dim(self) -> int:
        return len(self.action_low)

    @property
    def behavior_dim(self) -> int:
        return len(self.behavior_low)

    def evaluate(self, actions: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Rolls out `actions[B, n]`; returns behaviors[B, d], qualities[B], valid[B]."""
        raise NotImplementedError

    def features(self, actions: jax.Array) -> jax.Array:
        """What the task can compute from actions [B, n] without a rollout: features [B, f], float, about [-1, 1].

        Inputs for M-QD's model beside the normalized actions (`Surrogate(features=True)`): a
        pure, jittable and (almost everywhere) differentiable function, e.g. forward kinematics
        of the path an action commands, where it would first touch an object, how far it would
        go on. Scale each feature to about [-1, 1] (the model's inputs are in those units).
        The default: no features, [B, 0].
        """
        return jnp.zeros((actions.shape[0], 0), jnp.float32)

    def evaluate_masked(self, actions: jax.Array, key: jax.Array,
                        mask: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """`evaluate` for the rows where mask[B] is set; the other rows' outputs are ignored.

        The default rolls out every row (a traced, vmapped rollout costs the
        same either way); the engine discards the unmasked rows' outputs.
        """
        del mask
        return self.evaluate(actions, key)

    def evaluate_with_auxiliary(self, actions: jax.Array, key: jax.Array,
                                mask: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
        """`evaluate_masked`'s outputs and the rollouts' auxiliary outputs [B, m], one column per name of
        `auxiliary`, about [-1, 1] (what the engine calls). The default: none, [B, 0]."""
        return (*self.evaluate_masked(actions, key, mask), jnp.zeros((actions.shape[0], 0), jnp.float32))

    def reachable(self, points: np.ndarray) -> np.ndarray:
        """Whether each behavior `points[..., d]` is reachable (numpy, host side).

        Coverage is measured over the reachable part of the behavior box only.
        The default: the whole box.
        """
        return np.ones(points.shape[:-1], bool)

    def layout(self) -> tuple[Region, ...]:
        """The scene's parts to draw under the behaviors in figures; the default: none."""
        return ()

    def frames(self, action: np.ndarray, width: int, height: int) -> np.ndarray:
        """Frames [F, height, width, 3] uint8 of the skill `action` [n] being executed (`mqd render`).

        The default: not available for this task (raises NotImplementedError).
        """
        raise NotImplementedError(f"{type(self).__name__} does not render its skills (Task.frames)")


@functools.cache
def feature_dim(task: Task) -> int:
    """f, the number of `task.features` (read abstractly once per task: nothing runs; the surrogate asks at every
    trace of its init, predictions and update)."""
    return jax.eval_shape(task.features, jax.ShapeDtypeStruct((1, task.action_dim), jnp.float32)).shape[-1]


def _overrides_auxiliary(task: Task) -> bool:
    return type(task).evaluate_with_auxiliary is not Task.evaluate_with_auxiliary


def check_outputs(task: Task, name: str, batch: int) -> None:
    """Raises ValueError unless `task.evaluate` and `task.features` have the protocol's output shapes and dtypes.

    Checked abstractly (`jax.eval_shape`: nothing runs) on actions[batch, n].
    """
    n, d, m = task.action_dim, task.behavior_dim, len(task.auxiliary)
    want = f"(behaviors [{batch}, {d}] float, qualities [{batch}] float, valid [{batch}] bool"
    actions = jax.ShapeDtypeStruct((batch, n), jnp.float32)
    key = jax.random.PRNGKey(0)
    checks = [(f"evaluate(actions [{batch}, {n}], key)", lambda a: task.evaluate(a, key), want + ")",
               [(batch, d), (batch,), (batch,)], [jnp.floating, jnp.floating, jnp.bool_])]
    if _overrides_auxiliary(task):
        checks.append((f"evaluate_with_auxiliary(actions [{batch}, {n}], key, mask)",
                       lambda a: task.evaluate_with_auxiliary(a, key, jnp.ones(batch, bool)),
                       want + f", auxiliary [{batch}, {m}] float {task.auxiliary})",
                       [(batch, d), (batch,), (batch,), (batch, m)],
                       [jnp.floating, jnp.floating, jnp.bool_, jnp.floating]))
    for call, function, expected, shapes, kinds in checks:
        try:
            out = jax.eval_shape(function, actions)
        except Exception as e:  # any failure of user code is reported the same way
            raise ValueError(f"task {name!r}: {call} failed: {e}") from e
        if not (isinstance(out, tuple) and len(out) == len(shapes) and all(
                o.shape == s and jnp.issubdtype(o.dtype, k) for o, s, k in zip(out, shapes, kinds, strict=True))):
            got = jax.tree.map(lambda o: f"{o.dtype}{list(o.shape)}", out)
            raise ValueError(f"task {name!r}: {call} must return {expected}; got {got}")
    try:
        features = jax.eval_shape(task.features, actions)
    except Exception as e:  # any failure of user code is reported the same way
        raise ValueError(f"task {name!r}: features(actions [{batch}, {n}]) failed: {e}") from e
    if not (isinstance(features, jax.ShapeDtypeStruct) and features.ndim == 2 and features.shape[0] == batch
            and jnp.issubdtype(features.dtype, jnp.floating)):
        got = jax.tree.map(lambda o: f"{o.dtype}{list(o.shape)}", features)
        raise ValueError(f"task {name!r}: features(actions [{batch}, {n}]) must return features [{batch}, f] float; "
                         f"got {got}")


# Behavior spaces the library supports: novelty, insertion, coverage (`mqd_jax.core.coverage`), the model's outputs,
# adaptation and figures (pairwise projections beyond 2) work in any of these dimensions.
BEHAVIOR_DIMS = tuple(range(1, 9))


def _bounds(task: Task, name: str, field: str) -> np.ndarray:
    value = getattr(task, field)
    try:
        bounds = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        bounds = None
    if bounds is None or bounds.ndim != 1 or bounds.size == 0:
        raise ValueError(f"task {name!r}: {field}={value!r} is invalid: expected a non-empty tuple of numbers")
    if not np.isfinite(bounds).all():
        raise ValueError(f"task {name!r}: {field}={value!r} is invalid: every bound must be finite")
    return bounds


def check_task(task: Task, name: str) -> None:
    """Raises ValueError, naming the task and the field, unless its definition is usable.

    Checked when a task is made (`mqd_jax.core.registry`) or given to a `Config`, before
    anything is traced or allocated: the action and behavior bounds are finite
    tuples of equal lengths with low < high in every dimension, the behavior space
    has a supported dimension (`BEHAVIOR_DIMS`), `quality_range` is a finite
    (low, high) with low < high, and the paper settings are well-formed. The
    outputs of `evaluate` are checked abstractly at the first run (`check_outputs`).
    """
    for kind in ("action", "behavior"):
        low, high = _bounds(task, name, f"{kind}_low"), _bounds(task, name, f"{kind}_high")
        if low.shape != high.shape:
            raise ValueError(f"task {name!r}: {kind}_low has {low.size} dimensions and {kind}_high {high.size}: "
                             "give both bounds of every dimension")
        wrong = np.flatnonzero(~(low < high))
        if wrong.size:
            i = int(wrong[0])
            raise ValueError(f"task {name!r}: the {kind} box is empty in dimension {i} ({kind}_low[{i}]="
                             f"{low[i]} is not below {kind}_high[{i}]={high[i]}): give low < high in every dimension")
    if task.behavior_dim not in BEHAVIOR_DIMS:
        raise ValueError(f"task {name!r}: a behavior space of {task.behavior_dim} dimensions is not supported "
                         f"(supported: {BEHAVIOR_DIMS[0]} to {BEHAVIOR_DIMS[-1]}): describe skills with fewer numbers, "
                         "e.g. a projection of the behavior")
    aux = task.auxiliary
    if not (isinstance(aux, tuple) and all(isinstance(a, str) and a for a in aux) and len(set(aux)) == len(aux)):
        raise ValueError(f"task {name!r}: auxiliary={aux!r} is invalid: expected a tuple of distinct names")
    if aux and not _overrides_auxiliary(task):
        raise ValueError(f"task {name!r} names auxiliary outputs {aux} but does not return them: implement "
                         "evaluate_with_auxiliary")
    q = task.quality_range
    ok = (isinstance(q, tuple) and len(q) == 2 and all(isinstance(v, (int, float)) and np.isfinite(v) for v in q)
          and q[0] < q[1])
    if not ok:
        raise ValueError(f"task {name!r}: quality_range={q!r} is invalid: expected finite (low, high) with low < high")
    if task.table_ii_column not in ("2d", "robot"):
        raise ValueError(f"task {name!r}: table_ii_column={task.table_ii_column!r} is invalid: '2d' or 'robot'")
    t = task.default_t_dist
    if t is not None and not (isinstance(t, (int, float)) and np.isfinite(t) and t > 0):
        raise ValueError(f"task {name!r}: default_t_dist={t!r} is invalid: None or a finite float > 0")
    if not (isinstance(task.paper_seeds, int) and not isinstance(task.paper_seeds, bool) and task.paper_seeds >= 1):
        raise ValueError(f"task {name!r}: paper_seeds={task.paper_seeds!r} is invalid: an int >= 1")
