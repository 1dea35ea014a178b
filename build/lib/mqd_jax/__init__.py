"""mqd-jax: Model-Based Quality-Diversity search in JAX."""

from mqd_jax.adaptation import Adapted, adapt
from mqd_jax.config import Config, Params
from mqd_jax.run import Candidates, State, ask, generation, init, run_generations, run_mqd, tell
from mqd_jax.task import Task

__all__ = ["Adapted", "Candidates", "Config", "Params", "State", "Task", "adapt", "ask", "generation", "init",
           "run_generations", "run_mqd", "tell"]
