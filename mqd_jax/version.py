"""The version of mqd-jax: the one place it is written.

`pyproject.toml` reads it (`[tool.setuptools.dynamic]`), `mqd_jax.__version__`
is it, and every results file records it (`mqd_jax.experiment.provenance`). A sweep reuses
only batches written by this version (`mqd_jax.experiment.results`).
"""

__version__ = "0.24.0"
