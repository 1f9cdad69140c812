"""Lidar normals by PCA of the merged sweeps."""

from __future__ import annotations

import numpy as np

from diffloc.maps.nerf.lidar_rays import pca_normals


def test_pca_normals_of_a_plane_face_the_sensor() -> None:
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, (400, 2))
    points = np.column_stack((xy, np.full(400, 2.0)))  # the plane z = 2
    origins = np.zeros_like(points)  # sensor below the plane
    normals = pca_normals(points, origins, radius=0.3, min_neighbours=6, k=16)
    np.testing.assert_allclose(normals, np.tile([0.0, 0.0, -1.0], (400, 1)), atol=1e-6)


def test_isolated_points_get_no_normal() -> None:
    points = np.array([[0.0, 0, 0], [5.0, 0, 0], [0.0, 5, 0]])
    normals = pca_normals(points, np.ones_like(points), radius=0.3, min_neighbours=3, k=4)
    assert not normals.any()
