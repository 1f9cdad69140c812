"""Radiance-field submaps (seed 2 III-D3, SiLVR-style): field, sampling, losses, submaps and
the Lightning training of one submap on a CPU."""
