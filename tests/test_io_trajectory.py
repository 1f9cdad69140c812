"""TUM trajectory files, pose interpolation and timestamp association."""

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from diffloc.geometry.se3 import pose_from_translation_quaternion
from diffloc.io.trajectory import associate_timestamps, interpolate_poses, read_tum, write_tum


def random_poses(n: int, seed: int = 0, scale: float = 100.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g, dtype=torch.float64)
    t = torch.randn(n, 3, generator=g, dtype=torch.float64) * scale
    return pose_from_translation_quaternion(t, q)


def test_round_trip_within_1e9(tmp_path: Path):
    T = random_poses(30)
    times = 1403636579.763555 + np.arange(30) * 0.05
    write_tum(tmp_path / "poses.txt", times, T)
    text = (tmp_path / "poses.txt").read_text()
    assert text.startswith("# timestamp tx ty tz qx qy qz qw\n")
    got_times, got_T = read_tum(tmp_path / "poses.txt")
    assert got_T.dtype == torch.float64 and got_times.dtype == np.float64
    np.testing.assert_allclose(got_times, times, rtol=0, atol=1e-9)
    torch.testing.assert_close(got_T, T, rtol=0, atol=1e-9)
    write_tum(tmp_path / "again.txt", got_times, got_T)
    assert (tmp_path / "again.txt").read_text() == text, "write(read(x)) must be stable"


def test_commas_comments_and_blank_lines(tmp_path: Path):
    path = tmp_path / "poses.txt"
    path.write_text("# header\n\n1.0, 1, 2, 3, 0, 0, 0, 2\n  # another\n2.0\t0 0 0 0 0 1 0\n")
    times, T = read_tum(path)
    np.testing.assert_array_equal(times, [1.0, 2.0])
    torch.testing.assert_close(T[0, :3, 3], torch.tensor([1.0, 2, 3], dtype=torch.float64))
    torch.testing.assert_close(T[0, :3, :3], torch.eye(3, dtype=torch.float64))
    torch.testing.assert_close(
        T[1, :3, :3], torch.diag(torch.tensor([-1.0, -1, 1], dtype=torch.float64))
    )


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("2.0 1 2 3 0 0 0", "expected 8 columns"),
        ("2.0 1 2 3 0 0 0 1 5", "expected 8 columns"),
        ("2.0 1 two 3 0 0 0 1", "not a number"),
        ("2.0 1 2 nan 0 0 0 1", "NaN"),
        ("2.0 1 2 3 0 0 0 0", "zero quaternion"),
        ("0.5 1 2 3 0 0 0 1", "not greater"),
    ],
)
def test_malformed_rows_name_file_and_line(tmp_path: Path, row: str, message: str):
    path = tmp_path / "poses.txt"
    path.write_text(f"# comment\n1.0 0 0 0 0 0 0 1\n{row}\n")
    with pytest.raises(ValueError, match=message) as info:
        read_tum(path)
    assert "poses.txt, line 3" in str(info.value)


def test_missing_file(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="nothing.txt"):
        read_tum(tmp_path / "nothing.txt")


def test_write_rejects_bad_input(tmp_path: Path):
    with pytest.raises(ValueError, match="increasing"):
        write_tum(tmp_path / "a.txt", np.array([1.0, 1.0]), random_poses(2))
    bad = random_poses(2).clone()
    bad[0, 0, 0] += 0.1
    with pytest.raises(ValueError, match="rigid"):
        write_tum(tmp_path / "a.txt", np.array([1.0, 2.0]), bad)
    assert not (tmp_path / "a.txt").exists()


def test_interpolation_matches_scipy_slerp():
    T = random_poses(6, seed=3, scale=1.0)
    times = np.array([0.0, 0.4, 1.0, 1.1, 2.5, 3.0])
    query = np.array([0.0, 0.1, 0.4, 0.77, 1.05, 2.0, 2.9999, 3.0])
    got = interpolate_poses(times, T, query)
    rotations = Rotation.from_matrix(T[:, :3, :3].numpy())
    expected_R = Slerp(times, rotations)(query).as_matrix()
    np.testing.assert_allclose(got[:, :3, :3].numpy(), expected_R, atol=1e-12)
    expected_t = np.stack([np.interp(query, times, T[:, i, 3].numpy()) for i in range(3)], 1)
    np.testing.assert_allclose(got[:, :3, 3].numpy(), expected_t, atol=1e-12)
    assert torch.equal(got[0], T[0]) and torch.equal(got[2], T[1]) and torch.equal(got[-1], T[-1])


def test_interpolation_halfway_rotation_about_z():
    def rot_z(angle: float) -> torch.Tensor:
        c, s = np.cos(angle), np.sin(angle)
        T = torch.eye(4, dtype=torch.float64)
        T[:2, :2] = torch.tensor([[c, -s], [s, c]])
        return T

    T = torch.stack([rot_z(0.2), rot_z(1.0)])
    T[1, :3, 3] = torch.tensor([2.0, 0.0, -4.0])
    mid = interpolate_poses(np.array([10.0, 12.0]), T, np.array([11.5]))[0]
    expected = rot_z(0.2 + 0.75 * 0.8)
    expected[:3, 3] = torch.tensor([1.5, 0.0, -3.0])
    torch.testing.assert_close(mid, expected, atol=1e-12, rtol=0)


def test_interpolation_out_of_range_is_an_error():
    T = random_poses(2)
    with pytest.raises(ValueError, match="outside"):
        interpolate_poses(np.array([0.0, 1.0]), T, np.array([0.5, 1.5]))
    with pytest.raises(ValueError, match="outside"):
        interpolate_poses(np.array([0.0, 1.0]), T, np.array([-1e-6]))


def test_associate_is_one_to_one_nearest():
    a = np.array([0.0, 1.0, 1.02, 2.0, 5.0])
    b = np.array([0.015, 1.01, 2.5, 4.99, 10.0])
    idx_a, idx_b = associate_timestamps(a, b, max_dt=0.02)
    # 1.0 and 1.02 both want 1.01 (dt 0.01 each): the tie goes to the lower index.
    np.testing.assert_array_equal(idx_a, [0, 1, 4])
    np.testing.assert_array_equal(idx_b, [0, 1, 3])
    assert idx_a.dtype == np.int64
    idx_a, idx_b = associate_timestamps(a, b[::-1].copy(), max_dt=0.001)
    assert len(idx_a) == 0 and len(idx_b) == 0


def test_associate_greedy_prefers_closest_pair():
    a = np.array([0.0, 0.03])
    b = np.array([0.025])
    idx_a, idx_b = associate_timestamps(a, b, max_dt=0.05)
    np.testing.assert_array_equal(idx_a, [1])
    np.testing.assert_array_equal(idx_b, [0])
