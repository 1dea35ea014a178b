"""The learned forward model (an ensemble of MLPs, normalization, Adam training) and the validity classifier.
Imports `core` only."""
