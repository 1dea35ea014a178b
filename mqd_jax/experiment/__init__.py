"""Experiment tooling: results folders, sweep results and tables, checkpoints, sweeps, figures, statistics,
provenance and the `mqd` command line. Imports anything of mqd_jax."""
