"""Relocalization: minimal and non-minimal PnP solvers, RANSAC and pose refinement."""
