"""mqd-jax: Model-Based Quality-Diversity search in JAX.

The names below are imported when first used (PEP 562), so that `import mqd_jax` alone, and the `mqd` command's
first instruction, cost no import of JAX: the command handles Ctrl-C from its start
(`mqd_jax.experiment.command`).
"""

import importlib
from typing import Any

# Each public name: the module that defines it.
_WHERE = {
    "Adapted": "mqd_jax.adaptation",
    "adapt": "mqd_jax.adaptation",
    "registry": "mqd_jax.core",
    "Config": "mqd_jax.core.config",
    "Emitter": "mqd_jax.core.emitter",
    "Evaluated": "mqd_jax.core.emitter",
    "Proposal": "mqd_jax.core.emitter",
    "Params": "mqd_jax.core.params",
    "AddStatus": "mqd_jax.core.repertoire",
    "Candidates": "mqd_jax.core.run",
    "State": "mqd_jax.core.state",
    "ask": "mqd_jax.core.run",
    "generation": "mqd_jax.core.run",
    "init": "mqd_jax.core.state",
    "run_generations": "mqd_jax.core.run",
    "run_mqd": "mqd_jax.core.run",
    "tell": "mqd_jax.core.run",
    "Task": "mqd_jax.core.task",
    "presets": "mqd_jax.emitters",
    "Budgeted": "mqd_jax.emitters.acquisition",
    "Diverse": "mqd_jax.emitters.diverse",
    "Threshold": "mqd_jax.emitters.acquisition",
    "Anchoring": "mqd_jax.emitters.anchoring",
    "IsoLine": "mqd_jax.emitters.baselines",
    "Uniform": "mqd_jax.emitters.baselines",
    "Curiosity": "mqd_jax.emitters.curiosity",
    "Imagination": "mqd_jax.emitters.imagination",
    "ModelEmitter": "mqd_jax.emitters.model_emitter",
    "Part": "mqd_jax.emitters.parts",
    "Share": "mqd_jax.emitters.parts",
    "Fallback": "mqd_jax.emitters.pursuit",
    "SideBySide": "mqd_jax.emitters.side_by_side",
    "Steering": "mqd_jax.emitters.steering",
    "StepAside": "mqd_jax.emitters.step_aside",
    "LocalLinear": "mqd_jax.surrogate.local",
    "Surrogate": "mqd_jax.surrogate.surrogate",
    "Validity": "mqd_jax.surrogate.validity",
    "__version__": "mqd_jax.version",
}

__all__ = [
           "Adapted",
           "AddStatus",
           "Anchoring",
           "Budgeted",
           "Candidates",
           "Config",
           "Curiosity",
           "Diverse",
           "Emitter",
           "Evaluated",
           "Fallback",
           "Imagination",
           "IsoLine",
           "LocalLinear",
           "ModelEmitter",
           "Params",
           "Part",
           "Proposal",
           "Share",
           "SideBySide",
           "State",
           "Steering",
           "StepAside",
           "Surrogate",
           "Task",
           "Threshold",
           "Uniform",
           "Validity",
           "__version__",
           "adapt",
           "ask",
           "generation",
           "init",
           "presets",
           "registry",
           "run_generations",
           "run_mqd",
           "tell",
]


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module 'mqd_jax' has no attribute {name!r}")
    module = importlib.import_module(_WHERE[name])
    value = getattr(module, name) if hasattr(module, name) else importlib.import_module(f"{_WHERE[name]}.{name}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_WHERE})
