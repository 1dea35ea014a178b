"""The named algorithms: functions with keyword arguments that return an emitter (as optax's `adam(...)` returns
a gradient transformation).

    random()                                              -> Uniform()
    qd(iso_sigma, line_sigma)                             -> IsoLine()
    mqd(pool_factor=8, optimism=1.0, ..., surrogate=None, rule=None)
                                                          -> ModelEmitter(IsoLine(scales=(1, wide_scale)),
                                                                          Diverse(...), Surrogate(features, gate),
                                                                          parts=(Steering(...), Anchoring("auto"),
                                                                                 [Curiosity(curiosity),]
                                                                                 Fallback()))
    mqd_paper(t_nov=0.04, t_qua=0.0, budgeted=False, ...) -> ModelEmitter(IsoLine(), Threshold(t_nov, t_qua),
                                                                          Surrogate())
                                                             (or Budgeted(pool_factor) when budgeted)
    mqd_local(neighbours=0, ridge=1e-3, buffer=4096, ...) -> mqd(surrogate=LocalLinear(...), ...)

Each preset's defaults are in its signature: the model's are Table II's 2D column (`TABLE_II` holds both
columns). They are registered with `mqd_jax.core.algorithms`: a `Config` names a preset as `algorithm="mqd"`
with `algorithm_options={"pool_factor": 16}`, checked against the signature (`algorithms.options`,
`algorithms.build`); `k` is the run's (`Config.k`), passed by the config. An option whose default is None takes a
part given in Python (`presets.mqd(surrogate=KNN())`, or `algorithm_options={"surrogate": KNN()}`), which
replaces that part and keeps the preset's others.
"mqd" is the best composition measured (docs/results.md); "mqd-paper" reproduces the paper's Algorithm 1;
"mqd-local" is "mqd" with the network-free `LocalLinear` surrogate, by name, so that a file can name it (a part
given in Python cannot be rebuilt from a saved config).
"""

from __future__ import annotations

import inspect
from typing import Any

from mqd_jax.core import algorithms
from mqd_jax.core.checks import is_int, is_real
from mqd_jax.core.emitter import Emitter
from mqd_jax.emitters.acquisition import Budgeted, Threshold
from mqd_jax.emitters.anchoring import Anchoring
from mqd_jax.emitters.baselines import IsoLine, Uniform
from mqd_jax.emitters.curiosity import Curiosity
from mqd_jax.emitters.diverse import Diverse
from mqd_jax.emitters.model_emitter import ModelEmitter
from mqd_jax.emitters.pursuit import Fallback
from mqd_jax.emitters.steering import Steering
from mqd_jax.emitters.step_aside import StepAside
from mqd_jax.surrogate.gate import Gate
from mqd_jax.surrogate.local import LocalLinear
from mqd_jax.surrogate.surrogate import Surrogate
from mqd_jax.surrogate.validity import Validity

# Table II: the model's settings in the paper's two columns (the 2D column is every preset's default).
TABLE_II = {
    "2d": {"learning_rate": 1e-3, "batch_size": 16, "num_batches": 500, "warmup_samples": 1000, "hidden_size": 32},
    "robot": {"learning_rate": 1e-3, "batch_size": 16, "num_batches": 500, "warmup_samples": 1000,
              "hidden_size": 64},
}


# The options of the built-in model and of `Diverse` that a preset does not read where one's own part replaces them
# (Table II's settings among them are left alone: a config passes those for every run).
_SURROGATE_OPTIONS = ("ensemble_size", "features", "gate", "validity", "training_data", "rollout_buffer",
                      "novelty_sampling")
_RULE_OPTIONS = ("pool_factor", "optimism", "parent_weight", "quality_share", "opener_cap")


def _own_part(name: str, part: Any, given: dict[str, Any], options: tuple[str, ...]) -> None:
    """ValueError where `part` (one's own, in place of the preset's) comes with options of the part it replaces
    set to other than their defaults: they would not be read."""
    if part is None:
        return
    defaults = {p.name: p.default for p in inspect.signature(mqd).parameters.values()}
    unread = [f"{o}={given[o]!r}" for o in options if given[o] != defaults[o]]
    if unread:
        raise ValueError(f"mqd: {name}={part!r} replaces the preset's own, which {', '.join(unread)} would set: "
                         f"they are not read; leave them out")


def random() -> Emitter:
    """RANDOM: actions uniform in the action box."""
    return Uniform()


def qd(iso_sigma: float = 0.02, line_sigma: float = 0.1) -> Emitter:
    """QD: iso+line children of parents drawn in proportion to novelty (`IsoLine`)."""
    return IsoLine(iso_sigma=iso_sigma, line_sigma=line_sigma)


def mqd(k: int = 5, pool_factor: int = 8, optimism: float = 1.0, parent_weight: float = 1.0,
        quality_share: float = 0.1, opener_cap: float = 0.0, wide_scale: float = 2.0, steering_share: float = 0.25,
        anchor: str = "parent", ensemble_size: int = 1, hidden_size: int = 32, batch_size: int = 16,
        num_batches: int = 500, warmup_samples: int = 1000, learning_rate: float = 1e-3, iso_sigma: float = 0.02,
        line_sigma: float = 0.1, features: bool = True, gate: bool = True, validity: bool = False,
        step_aside: bool = False, training_data: str = "repertoire", rollout_buffer: int = 4096,
        curiosity: float = 0.0, novelty_sampling: float = 0.0, surrogate: Any = None, rule: Any = None) -> Emitter:
    """This library's M-QD: the model ranks `pool_factor` x the population and the rule rolls out a diverse set.

    Args:
      k: the neighbours of the model's predicted novelty (the run's `Config.k`).
      pool_factor: candidates per rollout the model chooses from (`Diverse`).
      optimism: the weight of the ensemble's spread in the optimistic distance (`Diverse.beta`).
      parent_weight: the exponent of a predicted opener's parent's relative novelty in its rank.
      quality_share: the share of the choices that go first to predicted quality gains in held niches.
      opener_cap: a predicted opener's distance counts in its rank up to this multiple of t_dist (`Diverse.cap`;
        0: no cap). The model errs most on the candidates it predicts farthest (docs/results.md).
      wide_scale: half the pool's children vary at this multiple of both iso+line steps (1: one scale).
      steering_share: the share of the pool aimed by the model's Jacobian (`Steering`; 0: none).
      anchor: where predictions are anchored: the candidate's "parent" or the "nearest" skill.
      ensemble_size: the model's members (1: one network).
      hidden_size, batch_size, num_batches, warmup_samples, learning_rate: the model and its training (Table II).
      iso_sigma, line_sigma: the iso+line steps of the inner `IsoLine`.
      features: the model also takes the task's features of an action (`Task.features`; a task without
        them: no change).
      gate: a `Gate` on the task's auxiliary output "moved" moves candidates predicted not to act to the null
        outcome (`Task.auxiliary`; a task without them: no change).
      validity: a `Validity` classifier of usable rollouts; the rule puts candidates it judges likely unusable
        after the others of their tier.
      step_aside: a `StepAside`: while the model's predictions explain no more of its rollouts' behaviors than
        chance, the generation is the inner emitter's own (plain QD emission).
      training_data, rollout_buffer: the model trains on the "repertoire" (Table II) or on its latest
        `rollout_buffer` usable "rollouts" (`Surrogate.training_data`).
      curiosity: a `Curiosity` of this weight reweighs each candidate by its parent's record of children that
        opened niches (0: none; it acts through the parent factor, so parent_weight must be > 0).
      novelty_sampling: the model's mini-batches draw skills in proportion to novelty to this power
        (`Surrogate.novelty_sampling`; 0: uniformly), where the candidates' parents come from.
      surrogate: a surrogate of one's own (`mqd_jax.surrogate.protocol`) in place of the built-in model, the
        preset's other parts kept (the inner emitter, the rule, fallback, steering, anchoring); None: the
        built-in `Surrogate` of the options above. With one's own, ensemble_size, features, gate, validity,
        training_data, rollout_buffer and novelty_sampling given other than their defaults are a ValueError (they
        would not be read); Table II's hidden_size, batch_size, num_batches and learning_rate, which a config passes
        for every run, are not read.
      rule: an acquisition rule of one's own (`acquisition.Acquisition`) in place of `Diverse`, the other parts
        kept; None: `Diverse` of the options above (pool_factor, optimism, parent_weight, quality_share, opener_cap:
        not read with one's own, ValueError where given). Fallback and steering need a ranking rule.
    """
    _own_part("surrogate", surrogate, locals(), _SURROGATE_OPTIONS)
    _own_part("rule", rule, locals(), _RULE_OPTIONS)
    if not (is_real(curiosity) and curiosity >= 0):
        raise ValueError(f"mqd: curiosity={curiosity!r} is invalid: expected a finite float >= 0 (0: none)")
    if curiosity and rule is None and not parent_weight:
        raise ValueError(f"mqd: curiosity={curiosity!r} acts through the parent factor, which parent_weight=0 "
                         "turns off: set parent_weight > 0 or curiosity=0")
    rule = rule if rule is not None else Diverse(pool_factor, optimism, parent_weight=parent_weight,
                                                 quality_share=quality_share, cap=opener_cap)
    # One scale, not (1, 1): IsoLine's parts draw from keys of their own, and 1 repeats version 0.8's runs.
    scales = (1.0,) if wide_scale == 1 else (1.0, wide_scale)
    surrogate = surrogate if surrogate is not None else Surrogate(
        hidden_size=hidden_size, ensemble_size=ensemble_size, batch_size=batch_size, num_batches=num_batches,
        learning_rate=learning_rate, features=features, gate=Gate() if gate else None,
        validity=Validity() if validity else None, training_data=training_data, rollout_buffer=rollout_buffer,
        novelty_sampling=novelty_sampling)
    chain = ((Steering(share=steering_share),) if steering_share else ()) + (
        Anchoring("auto", anchor),) + ((Curiosity(curiosity),) if curiosity else ()) + (
        Fallback(),) + ((StepAside(),) if step_aside else ())
    return ModelEmitter(IsoLine(scales=scales, iso_sigma=iso_sigma, line_sigma=line_sigma), rule, surrogate, k=k,
                        warmup_samples=warmup_samples, parts=chain)


def mqd_paper(k: int = 5, t_nov: float = 0.04, t_qua: float = 0.0, budgeted: bool = False, pool_factor: int = 8,
              hidden_size: int = 32, batch_size: int = 16, num_batches: int = 500, warmup_samples: int = 1000,
              learning_rate: float = 1e-3, iso_sigma: float = 0.02, line_sigma: float = 0.1,
              surrogate: Any = None) -> Emitter:
    """The paper's M-QD (Algorithm 1): roll out the candidates whose predicted novelty exceeds `t_nov` or whose
    predicted quality improvement exceeds `t_qua` (`Threshold`); `budgeted`: instead rank `pool_factor` x the
    population and roll out the best population (`Budgeted`). The model's settings: Table II; `surrogate`: one's
    own in place of the built-in model (its Table II settings then not read)."""
    if not isinstance(budgeted, bool):
        raise ValueError(f"mqd-paper: budgeted={budgeted!r} is invalid: expected a bool")
    rule = Budgeted(pool_factor, t_nov=t_nov) if budgeted else Threshold(t_nov=t_nov, t_qua=t_qua)
    surrogate = surrogate if surrogate is not None else Surrogate(
        hidden_size=hidden_size, batch_size=batch_size, num_batches=num_batches, learning_rate=learning_rate)
    return ModelEmitter(IsoLine(iso_sigma=iso_sigma, line_sigma=line_sigma), rule, surrogate, k=k,
                        warmup_samples=warmup_samples)


def mqd_local(neighbours: int = 0, ridge: float = 1e-3, buffer: int = 4096, k: int = 5, pool_factor: int = 8,
              optimism: float = 1.0, parent_weight: float = 1.0, quality_share: float = 0.1, wide_scale: float = 2.0,
              steering_share: float = 0.25, anchor: str = "parent", warmup_samples: int = 1000,
              iso_sigma: float = 0.02, line_sigma: float = 0.1, curiosity: float = 0.0, rule: Any = None) -> Emitter:
    """`mqd` with `LocalLinear(neighbours, ridge, buffer)` as its surrogate (`mqd_jax.surrogate.local`: a fit to
    each candidate's `neighbours` nearest of the latest `buffer` rollouts, 0: 4 (n + 1) for n action dimensions),
    the other options `mqd`'s. Fewer rollouts than the network on several tasks and QD's quality, at more time per
    generation (docs/results.md)."""
    if not (is_int(neighbours) and (neighbours == 0 or neighbours >= 2)):
        raise ValueError(f"mqd-local: neighbours={neighbours!r} is invalid: expected 0 (4 (n + 1)) or an int >= 2")
    return mqd(k=k, pool_factor=pool_factor, optimism=optimism, parent_weight=parent_weight,
               quality_share=quality_share, wide_scale=wide_scale, steering_share=steering_share, anchor=anchor,
               warmup_samples=warmup_samples, iso_sigma=iso_sigma, line_sigma=line_sigma, curiosity=curiosity,
               surrogate=LocalLinear(neighbours or None, ridge, buffer), rule=rule)


# The presets `Config.algorithm` may name, in the order tables show them; the model's options per Table II column.
algorithms.register("mqd", mqd, TABLE_II)
algorithms.register("mqd-paper", mqd_paper, TABLE_II)
algorithms.register("qd", qd)
algorithms.register("random", random)
algorithms.register("mqd-local", mqd_local, {column: {"warmup_samples": settings["warmup_samples"]}
                                             for column, settings in TABLE_II.items()})
