"""mqd-jax: Model-Based Quality-Diversity search in JAX."""

from mqd_jax.adaptation import Adapted, adapt
from mqd_jax.core import registry
from mqd_jax.core.config import Config
from mqd_jax.core.emitter import Emitter, Evaluated, Proposal
from mqd_jax.core.params import Params
from mqd_jax.core.repertoire import AddStatus
from mqd_jax.core.run import Candidates, State, ask, generation, init, run_generations, run_mqd, tell
from mqd_jax.core.task import Task
from mqd_jax.emitters import presets
from mqd_jax.emitters.acquisition import Budgeted, Diverse, Threshold
from mqd_jax.emitters.anchoring import Anchoring
from mqd_jax.emitters.baselines import IsoLine, Uniform
from mqd_jax.emitters.curiosity import Curiosity
from mqd_jax.emitters.imagination import Imagination
from mqd_jax.emitters.model_emitter import ModelEmitter
from mqd_jax.emitters.parts import Part, Share
from mqd_jax.emitters.pursuit import Fallback
from mqd_jax.emitters.side_by_side import SideBySide
from mqd_jax.emitters.steering import Steering
from mqd_jax.emitters.step_aside import StepAside
from mqd_jax.surrogate.local import LocalLinear
from mqd_jax.surrogate.surrogate import Surrogate
from mqd_jax.surrogate.validity import Validity
from mqd_jax.version import __version__

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
