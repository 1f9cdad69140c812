"""Spectral clustering of a trajectory into overlapping submaps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from diffloc.maps.nerf.submaps import (
    SubmapConfig,
    affinity,
    cluster_trajectory,
    load_submaps,
    plot_submaps,
    save_submaps,
    serving_submap,
)


def _poses(xs: list[float], yaw: float = 0.0) -> torch.Tensor:
    """Cameras along x looking along +x rotated by ``yaw`` (z axis = view direction)."""
    T = torch.eye(4, dtype=torch.float64).repeat(len(xs), 1, 1)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:, :3, :3] = torch.tensor([[0.0, 0, c], [0, 1, s], [-1, 0, 0]], dtype=torch.float64)
    T[:, :3, 2] = torch.tensor([c, s, 0.0], dtype=torch.float64)
    T[:, 0, 3] = torch.tensor(xs, dtype=torch.float64)
    return T


def _two_rooms() -> torch.Tensor:
    return torch.cat((_poses(list(np.arange(0, 3, 0.25))), _poses(list(np.arange(20, 23, 0.25)))))


def test_affinity_falls_with_distance_and_viewing_angle() -> None:
    T = torch.cat((_poses([0.0, 1.0]), _poses([0.0], yaw=np.pi / 2)))
    a = affinity(T, 1.0, 30.0)
    assert a[0, 0] == pytest.approx(1.0)
    assert a[0, 1] == pytest.approx(np.exp(-0.5))
    assert a[0, 2] == pytest.approx(np.exp(-0.5 * 9))


def test_eigengap_finds_two_separate_rooms_and_cores_partition_the_frames() -> None:
    submaps = cluster_trajectory(_two_rooms(), SubmapConfig(position_sigma_m=2.0, overlap_m=0.3))
    assert len(submaps) == 2
    assert submaps[0].core == list(range(12)) and submaps[1].core == list(range(12, 24))
    assert submaps[0].frames == submaps[0].core
    assert submaps[0].box_max[0] == pytest.approx(2.75 + 3.0)


def test_overlap_adds_the_frames_near_the_boundary() -> None:
    T = _poses(list(np.arange(0, 10, 0.5)))
    submaps = cluster_trajectory(T, SubmapConfig(num_submaps=2, overlap_m=1.0))
    a, b = submaps
    assert sorted(a.core + b.core) == list(range(20))
    shared = set(a.frames) & set(b.frames)
    assert len(shared) == 4  # two frames either side of the boundary within 1 m
    assert set(a.core) < set(a.frames)


def test_serving_submap_is_the_nearest_cluster() -> None:
    T = _two_rooms()
    cfg = SubmapConfig(position_sigma_m=2.0)
    submaps = cluster_trajectory(T, cfg)
    queries = _poses([1.1, 21.3])
    assert serving_submap(queries, submaps, T, cfg).tolist() == [0, 1]


def test_save_load_round_trip_and_plot(tmp_path: Path) -> None:
    T, cfg = _two_rooms(), SubmapConfig(position_sigma_m=2.0)
    submaps = cluster_trajectory(T, cfg)
    save_submaps(tmp_path / "submaps.json", submaps, cfg)
    assert load_submaps(tmp_path / "submaps.json") == (submaps, cfg)
    (tmp_path / "bad.json").write_text('{"format_version": 7}')
    with pytest.raises(ValueError, match="not a diffloc submap file"):
        load_submaps(tmp_path / "bad.json")
    plot_submaps(tmp_path / "submaps.png", T, submaps)
    assert (tmp_path / "submaps.png").read_bytes()[:4] == b"\x89PNG"


def test_too_few_frames_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="at least 2 frames"):
        cluster_trajectory(_poses([0.0]), SubmapConfig())
    with pytest.raises(ValueError, match="submaps asked for"):
        cluster_trajectory(_poses([0.0, 1.0]), SubmapConfig(num_submaps=3))
