"""The surrogate: the learned forward model (an ensemble of MLPs, normalization, Adam training), the part a model
emitter composes (training data, anchoring, predictions, learning) and the validity classifier. Imports `core`
only."""
