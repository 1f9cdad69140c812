"""diffloc: differentiable, GPU-free visual localization in lidar, mesh and radiance-field maps."""

__version__ = "0.1.0"
