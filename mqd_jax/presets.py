"""The named algorithms, as compositions of emitters.

    "random"    -> Uniform()
    "qd"        -> IsoLine()
    "mqd"       -> ModelEmitter(IsoLine(scales=(1, wide_scale)),
                                Diverse(pool_factor, optimism, parent_weight=parent_weight,
                                        quality_share=quality_share),
                                ensemble_size members,
                                anchoring="auto", anchor=anchor, fallback=Fallback(),
                                steering=Steering(share=steering_share))    (this library's M-QD)
    "mqd-paper" -> ModelEmitter(IsoLine(), Threshold())                      (the paper's filter)
                   ModelEmitter(IsoLine(), Budgeted(pool_factor))            (cfg.budgeted)

with the model's settings from the config (Table II). "mqd" is the best
composition measured in `experiments/sample_efficiency.py` (docs/results.md);
"mqd-paper" reproduces the paper's Algorithm 1 (one network, Table II). A
config whose `algorithm` is an emitter runs that emitter.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from mqd_jax.acquisition import Budgeted, Diverse, Threshold
from mqd_jax.config import Config
from mqd_jax.emitters import Emitter, IsoLine, Uniform
from mqd_jax.model_emitter import Fallback, ModelEmitter
from mqd_jax.steering import Steering


def _mqd(cfg: Config) -> ModelEmitter:
    rule = Diverse(cfg.pool_factor, cfg.optimism, parent_weight=cfg.parent_weight, quality_share=cfg.quality_share)
    # One scale, not (1, 1): IsoLine's parts draw from keys of their own, and 1 must repeat version 0.8's runs.
    inner = IsoLine() if cfg.wide_scale == 1 else IsoLine(scales=(1.0, cfg.wide_scale))
    return ModelEmitter(inner, rule, k=cfg.k,
                        hidden_size=cfg.hidden_size, ensemble_size=cfg.ensemble_size, batch_size=cfg.batch_size,
                        num_batches=cfg.num_batches, warmup_samples=cfg.warmup_samples, anchoring="auto",
                        anchor=cfg.anchor, fallback=Fallback(),
                        steering=Steering(share=cfg.steering_share) if cfg.steering_share else None)


def _mqd_paper(cfg: Config) -> ModelEmitter:
    return ModelEmitter(IsoLine(), Budgeted(cfg.pool_factor) if cfg.budgeted else Threshold(), k=cfg.k,
                        hidden_size=cfg.hidden_size, batch_size=cfg.batch_size, num_batches=cfg.num_batches,
                        warmup_samples=cfg.warmup_samples)


# Every name in `config.PRESETS`.
_BUILDERS: dict[str, Callable[[Config], Emitter]] = {"random": lambda cfg: Uniform(), "qd": lambda cfg: IsoLine(),
                                                     "mqd": _mqd, "mqd-paper": _mqd_paper}


def emitter(cfg: Config) -> Emitter:
    """The emitter a run of `cfg` uses: the preset `cfg.algorithm` names, or `cfg.algorithm` itself."""
    return cfg.algorithm if isinstance(cfg.algorithm, Emitter) else _BUILDERS[cfg.algorithm](cfg)


# The model fields of `Config` (every other field configures all presets alike), and those each preset reads:
# batches of one sweep must agree on the model fields both of their presets read, and only on those.
_TRAINING = ("learning_rate", "batch_size", "num_batches", "warmup_samples", "hidden_size")
_MQD = (*_TRAINING, "pool_factor", "ensemble_size", "optimism", "steering_share", "anchor", "parent_weight",
        "quality_share", "wide_scale")
MODEL_FIELDS = frozenset((*_MQD, "t_nov", "t_qua", "budgeted"))


def model_fields_read(cfg: Mapping[str, Any]) -> frozenset[str]:
    """The model fields that the preset of a config dict (`Config.to_dict`) reads; all of them for an algorithm
    that is not a preset."""
    algorithm = cfg.get("algorithm")
    if algorithm in ("random", "qd"):
        return frozenset()
    if algorithm == "mqd":
        return frozenset(_MQD)
    if algorithm == "mqd-paper":  # the pool only when budgeted
        return frozenset((*_TRAINING, "t_nov", "t_qua", "budgeted", *(("pool_factor",) if cfg.get("budgeted") else ())))
    return MODEL_FIELDS
