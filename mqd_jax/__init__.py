"""mqd-jax: Model-Based Quality-Diversity search in JAX."""

from mqd_jax import presets
from mqd_jax.acquisition import Budgeted, Diverse, Threshold
from mqd_jax.adaptation import Adapted, adapt
from mqd_jax.config import Config
from mqd_jax.emitters import Emitter, Evaluated, IsoLine, Proposal, Uniform
from mqd_jax.imagination import Imagination
from mqd_jax.model_emitter import Fallback, ModelEmitter
from mqd_jax.params import Params
from mqd_jax.repertoire import AddStatus
from mqd_jax.run import Candidates, State, ask, generation, init, run_generations, run_mqd, tell
from mqd_jax.steering import Steering
from mqd_jax.task import Task
from mqd_jax.validity import Validity
from mqd_jax.version import __version__

__all__ = [
           "Adapted",
           "AddStatus",
           "Budgeted",
           "Candidates",
           "Config",
           "Diverse",
           "Emitter",
           "Evaluated",
           "Fallback",
           "Imagination",
           "IsoLine",
           "ModelEmitter",
           "Params",
           "Proposal",
           "State",
           "Steering",
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
           "run_generations",
           "run_mqd",
           "tell",
]
