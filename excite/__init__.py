"""Excitation trajectories: Fourier series optimised for identification, ruckig approach/retreat."""
