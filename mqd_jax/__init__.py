"""mqd-jax: Model-Based Quality-Diversity search in JAX."""

from mqd_jax.adaptation import Adapted, adapt
from mqd_jax.config import Config, Params
from mqd_jax.run import State, generation, init, run_generations, run_mqd
from mqd_jax.task import Task

__all__ = ["Adapted", "Config", "Params", "State", "Task", "adapt", "generation", "init", "run_generations", "run_mqd"]
