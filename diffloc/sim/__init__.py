"""Procedural simulator: worlds, imaging, lidar, trajectories and dataset writing."""
