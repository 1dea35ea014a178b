"""The paper's five tasks for mqd-jax.

They are registered with `mqd_jax.core.registry` through this package's entry points
(group `mqd_jax.tasks` in pyproject.toml): `Config(task="push_cube")` imports
`envs.push` only when the task is built. The robot tasks' factories take
`backend` ("auto", "mujoco" or "mjx"): `mqd_jax.core.registry.make("push_cube", backend="mjx")`.
"""
