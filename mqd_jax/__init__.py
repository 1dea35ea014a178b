"""mqd-jax: Model-Based Quality-Diversity search in JAX."""

from mqd_jax.config import Config, Params
from mqd_jax.run import State, generation, init, run_generations, run_mqd
from mqd_jax.task import Task

__all__ = ["Config", "Params", "State", "Task", "generation", "init", "run_generations", "run_mqd"]
