"""The engine: the task protocol and registry, the repertoire and its neighbours, the archive, coverage,
variation and selection, the emitter protocol and the algorithm registry, the config, and the generation and the
run. Imports nothing of mqd_jax outside `core` (but `mqd_jax.version`)."""
