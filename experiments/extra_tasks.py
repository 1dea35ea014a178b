"""Tasks none of the library was tuned on, for the experiments: registered by the scripts that name them.

* `arm`: the classic QD benchmark of a planar arm with 10 joints (angles in [-pi/2, pi/2], links 0.05 long from
  the centre of the unit square); behavior = the tip's position, quality = minus the angles' standard deviation.
* `rugged_arm`: the arm with every angle 25 x its action: a behavior that changes quickly along every action axis.
* `rastrigin`: QD's Rastrigin projection (20 dimensions).
* `arm_elbow`, `rugged_arm_elbow`: the two arms with features for M-QD's model (`Task.features`): where the
  middle joint (the elbow) is, the forward kinematics of half the arm: cheap to know, and only part of the answer.

Written for issue #58 after "mqd" was settled, none with features (what a user's own task declares):

* `chain`: a longer kinematic chain: 16 joints, links shrinking by 0.9 each, quality = minus the mean |angle|.
* `noisy_chain`: the chain with Gaussian noise in every rollout (0.01 on the tip, 0.02 on the quality).
* `holed_chain`: the chain whose rollouts are invalid (no outcome) where the first two angles sum above 0: half
  of the action space.
* `folded`: a folded many-to-one map of 8 actions: each behavior is a tent map folded 3 times of a fixed random
  projection, so that many far-apart actions share a behavior.
* `folded_noisy_holed`: the folded map with noise and an invalid band, kept unseen until the end of #58.
* `hashed`: behaviors no model can predict (a hash of 3 actions, uniform in the box): where the model must step
  aside.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import registry
from mqd_jax.core.task import Task


@dataclasses.dataclass(frozen=True, eq=False)
class PlanarArm(Task):
    """A planar arm of n joints in the unit square: behavior = tip position, quality = -std of the angles."""

    quality_range = (-1.6, 0.0)

    def evaluate(self, actions: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        n = actions.shape[1]
        heading = jnp.cumsum(actions, axis=1)
        tip = 0.5 + 0.5 / n * jnp.stack([jnp.cos(heading).sum(1), jnp.sin(heading).sum(1)], axis=1)
        return tip, -jnp.std(actions, axis=1), jnp.ones(actions.shape[0], bool)

    def reachable(self, points: np.ndarray) -> np.ndarray:
        return np.linalg.norm(points - 0.5, axis=-1) <= 0.5


def make_arm(joints: int = 10) -> PlanarArm:
    return PlanarArm((-np.pi / 2,) * joints, (np.pi / 2,) * joints, (0.0, 0.0), (1.0, 1.0))


@dataclasses.dataclass(frozen=True, eq=False)
class RuggedArm(PlanarArm):
    """The planar arm with every angle 25 x its action (wrapped around the circle): a behavior that changes
    quickly and repeatedly along every action axis, where a model learns little (the safety check)."""

    def evaluate(self, actions: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        angles = jnp.angle(jnp.exp(25j * actions))  # in (-pi, pi]
        tip, _, valid = super().evaluate(angles, key)
        return tip, -jnp.std(actions, axis=1), valid


def make_rugged_arm(joints: int = 10) -> RuggedArm:
    return RuggedArm((-np.pi / 2,) * joints, (np.pi / 2,) * joints, (0.0, 0.0), (1.0, 1.0))


def elbow(angles: jax.Array) -> jax.Array:
    """[B, 2] the position of the arm's middle joint for angles [B, n], from [0, 1] to [-1, 1]."""
    n = angles.shape[1]
    heading = jnp.cumsum(angles[:, : n // 2], axis=1)
    return 1.0 / n * jnp.stack([jnp.cos(heading).sum(1), jnp.sin(heading).sum(1)], axis=1)


@dataclasses.dataclass(frozen=True, eq=False)
class ElbowArm(PlanarArm):
    """The planar arm that tells the model where its elbow is."""

    def features(self, actions: jax.Array) -> jax.Array:
        return elbow(actions)


@dataclasses.dataclass(frozen=True, eq=False)
class ElbowRuggedArm(RuggedArm):
    """The rugged arm that tells the model where its elbow is."""

    def features(self, actions: jax.Array) -> jax.Array:
        return elbow(jnp.angle(jnp.exp(25j * actions)))


@dataclasses.dataclass(frozen=True, eq=False)
class RastriginProjection(Task):
    """QD's Rastrigin projection (a classic benchmark, after QDax's rastrigin_proj): x in [-5.12, 5.12]^n,
    behavior = the means of x's two halves mapped to [0, 1]^2, quality = -Rastrigin(x) / Rastrigin's largest
    value. A uniform action's means lie near the centre; the edges need a half of x moved together."""

    quality_range = (-1.0, 0.0)

    def evaluate(self, actions: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        n, bound = actions.shape[1], 5.12
        halves = jnp.stack([actions[:, : n // 2].mean(1), actions[:, n // 2:].mean(1)], axis=1)
        rastrigin = 10.0 * n + (actions**2 - 10.0 * jnp.cos(2 * jnp.pi * actions)).sum(1)
        return (halves / bound + 1.0) / 2.0, -rastrigin / (n * (bound**2 + 20.0)), jnp.ones(actions.shape[0], bool)


def make_rastrigin(dims: int = 20) -> RastriginProjection:
    return RastriginProjection((-5.12,) * dims, (5.12,) * dims, (0.0, 0.0), (1.0, 1.0))


@dataclasses.dataclass(frozen=True, eq=False)
class Chain(Task):
    """A planar chain of n joints whose links shrink by 0.9 each (`chain`), with optional noise in every rollout
    (`noise`: the tip's and the quality's standard deviations) and an invalid half (`holed`: a0 + a1 > 0)."""

    noise: tuple[float, float] = (0.0, 0.0)
    holed: bool = False
    quality_range = (-1.6, 0.0)

    def evaluate(self, actions: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        n = actions.shape[1]
        links = 0.9 ** jnp.arange(n)
        heading = jnp.cumsum(actions, axis=1)
        tip = 0.5 + 0.5 / links.sum() * jnp.stack([(links * jnp.cos(heading)).sum(1),
                                                   (links * jnp.sin(heading)).sum(1)], axis=1)
        quality = -jnp.abs(actions).mean(1)
        if self.noise != (0.0, 0.0):
            k_tip, k_quality = jax.random.split(key)
            tip = tip + self.noise[0] * jax.random.normal(k_tip, tip.shape)
            quality = quality + self.noise[1] * jax.random.normal(k_quality, quality.shape)
        valid = actions[:, 0] + actions[:, 1] <= 0 if self.holed else jnp.ones(actions.shape[0], bool)
        return jnp.clip(tip, 0.0, 1.0), quality, valid

    def reachable(self, points: np.ndarray) -> np.ndarray:
        return np.linalg.norm(points - 0.5, axis=-1) <= 0.5


def make_chain(joints: int = 16, noise: tuple[float, float] = (0.0, 0.0), holed: bool = False) -> Chain:
    return Chain((-np.pi / 2,) * joints, (np.pi / 2,) * joints, (0.0, 0.0), (1.0, 1.0), noise=noise, holed=holed)


def tent(x: jax.Array, folds: int) -> jax.Array:
    """x in [0, 1] folded `folds` times (a tent map of 2^folds teeth): many-to-one, continuous, in [0, 1]."""
    y = x
    for _ in range(folds):
        y = 1.0 - jnp.abs(2.0 * y - 1.0)
    return y


@dataclasses.dataclass(frozen=True, eq=False)
class Folded(Task):
    """Behavior = a tent map folded `folds` times of a fixed random projection of 8 actions in [-1, 1] (many
    actions per behavior); quality = minus the actions' mean square; optional noise and an invalid band."""

    folds: int = 3
    noise: tuple[float, float] = (0.0, 0.0)
    holed: bool = False

    def evaluate(self, actions: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        n = actions.shape[1]
        w = jax.random.normal(jax.random.PRNGKey(58), (n, 2)) / np.sqrt(n)
        behavior = tent(jnp.clip(0.5 + 0.25 * actions @ w, 0.0, 1.0), self.folds)
        quality = 1.0 - (actions**2).mean(1)
        if self.noise != (0.0, 0.0):
            k_b, k_q = jax.random.split(key)
            behavior = behavior + self.noise[0] * jax.random.normal(k_b, behavior.shape)
            quality = quality + self.noise[1] * jax.random.normal(k_q, quality.shape)
        valid = jnp.abs(actions[:, 2] - 0.3) > 0.35 if self.holed else jnp.ones(actions.shape[0], bool)
        return jnp.clip(behavior, 0.0, 1.0), quality, valid


def make_folded(dims: int = 8, folds: int = 3, noise: tuple[float, float] = (0.0, 0.0),
                holed: bool = False) -> Folded:
    return Folded((-1.0,) * dims, (1.0,) * dims, (0.0, 0.0), (1.0, 1.0), folds=folds, noise=noise, holed=holed)


@dataclasses.dataclass(frozen=True, eq=False)
class Hashed(Task):
    """Behavior = a hash of the action (the fractional part of a large multiple of a sine), quality = 0.5."""

    def evaluate(self, actions: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        w = jnp.array([[12.9898, 78.233], [39.346, 11.135], [73.156, 52.235]])
        behavior = jnp.mod(jnp.sin(actions @ w) * 43758.5453, 1.0)
        return behavior, jnp.full(actions.shape[0], 0.5), jnp.ones(actions.shape[0], bool)


# Tasks defined here, registered by the experiments that name them.
EXPERIMENT_TASKS = {
    "arm": make_arm, "rugged_arm": make_rugged_arm, "rastrigin": make_rastrigin,
    "arm_elbow": lambda: ElbowArm(*dataclasses.astuple(make_arm())),
    "rugged_arm_elbow": lambda: ElbowRuggedArm(*dataclasses.astuple(make_rugged_arm())),
    "chain": make_chain, "noisy_chain": lambda: make_chain(noise=(0.01, 0.02)),
    "holed_chain": lambda: make_chain(holed=True), "folded": make_folded,
    "folded_noisy_holed": lambda: make_folded(noise=(0.01, 0.02), holed=True),
    "hashed": lambda: Hashed((-1.0,) * 3, (1.0,) * 3, (0.0, 0.0), (1.0, 1.0)),
}


def register_experiment_tasks(tasks: list[str]) -> None:
    """Registers the tasks of `EXPERIMENT_TASKS` among `tasks` that are not registered yet."""
    for name in tasks:
        if name in EXPERIMENT_TASKS and not registry.is_task(name):
            registry.register(name, EXPERIMENT_TASKS[name])
