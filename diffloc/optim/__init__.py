"""Optimisation: robust kernels, batched Levenberg-Marquardt on SE(3), motion-only refinement."""
