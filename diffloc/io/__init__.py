"""Dataset, trajectory, point cloud and mesh input/output."""
