"""The surrogate: what any surrogate is (`protocol`: init, fit, predict), the learned forward model (an ensemble
of MLPs, normalization, Adam training), the built-in surrogate a model emitter composes (training data, features,
gate, validity classifier) and the validity classifier. Imports `core` only."""
