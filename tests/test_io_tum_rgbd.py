"""TUM RGB-D layout: association, interpolation, exact round trip, default camera, errors."""

from pathlib import Path

import numpy as np
import pytest
import torch

from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import pose_from_translation_quaternion
from diffloc.io.tum_rgbd import read_tum_rgbd, write_tum_rgbd

W, H, N = 16, 12, 5


def make_sequence(seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    g = torch.Generator().manual_seed(seed)
    T_wc = pose_from_translation_quaternion(
        torch.randn(N, 3, generator=g, dtype=torch.float64),
        torch.randn(N, 4, generator=g, dtype=torch.float64),
    )
    return {
        "times": 1305031102.175304 + np.arange(N) * 0.033,
        "T_wc": T_wc,
        "rgb": [rng.integers(0, 256, (H, W, 3)).astype(np.uint8) for _ in range(N)],
        "depth": [rng.integers(0, 60000, (H, W)) / 5000.0 for _ in range(N)],
        "camera": PinholeCamera.from_fov(W, H, 1.1, dtype=torch.float64),
    }


def write(root: Path, data: dict, camera: bool = True) -> Path:
    return write_tum_rgbd(
        root,
        data["times"],
        data["T_wc"],
        data["rgb"],
        data["depth"],
        camera=data["camera"] if camera else None,
        depth_time_offset=0.004,
    )


def test_round_trip_with_association(tmp_path: Path):
    data = make_sequence()
    root = write(tmp_path / "rgbd_dataset_test", data)
    rgb_lines = (root / "rgb.txt").read_text().splitlines()
    depth_lines = (root / "depth.txt").read_text().splitlines()
    assert rgb_lines[0].startswith("#") and rgb_lines[3].startswith("1305031102.175304 rgb/")
    assert depth_lines[3].startswith("1305031102.179304 depth/")
    seq = read_tum_rgbd(root)
    assert seq.name == "rgbd_dataset_test" and len(seq) == N
    assert seq.info == {"rgb_without_depth": 0, "dropped_images": 0, "camera_source": "calib.yaml"}
    np.testing.assert_allclose(seq.timestamps, data["times"], rtol=0, atol=1e-6)
    torch.testing.assert_close(seq.T_wc, data["T_wc"], rtol=0, atol=1e-9)
    assert seq.depth_scale == 5000.0
    assert seq.camera.fx.item() == data["camera"].fx.item()
    for i in range(N):
        rgb = torch.from_numpy(data["rgb"][i].transpose(2, 0, 1).astype(np.float32) / 255)
        assert torch.equal(seq.load_rgb(i), rgb)
        torch.testing.assert_close(
            seq.load_depth(i), torch.from_numpy(data["depth"][i])[None].float(), rtol=0, atol=1e-6
        )
        assert seq.depth_paths[i].name == f"{data['times'][i] + 0.004:.6f}.png"


def test_unmatched_frames_and_interpolated_ground_truth(tmp_path: Path):
    data = make_sequence()
    root = write(tmp_path / "seq", data)
    # An RGB frame with no depth partner, and ground truth only at frames 0, 2, 4.
    with (root / "rgb.txt").open("a") as handle:
        handle.write(f"{data['times'][-1] + 1.0:.6f} rgb/extra.png\n")
    gt = (root / "groundtruth.txt").read_text().splitlines()
    (root / "groundtruth.txt").write_text("\n".join([gt[0], gt[1], gt[3], gt[5]]) + "\n")
    seq = read_tum_rgbd(root, max_dt=0.01)
    assert seq.info["rgb_without_depth"] == 1 and len(seq) == N
    torch.testing.assert_close(seq.T_wc[[0, 2, 4]], data["T_wc"][[0, 2, 4]], rtol=0, atol=1e-9)
    # Frame 1 lies halfway between 0 and 2: the translation is the mean.
    torch.testing.assert_close(
        seq.T_wc[1, :3, 3], data["T_wc"][[0, 2], :3, 3].mean(0), rtol=0, atol=1e-9
    )
    # A tight max_dt pairs nothing.
    with pytest.raises(ValueError, match="no RGB-depth pair"):
        read_tum_rgbd(root, max_dt=0.001)


def test_default_camera_is_freiburg1_and_argument_wins(tmp_path: Path):
    data = make_sequence()
    root = write(tmp_path / "seq", data, camera=False)
    seq = read_tum_rgbd(root)
    assert seq.info["camera_source"] == "freiburg1 default"
    assert (seq.camera.fx.item(), seq.camera.cy.item(), seq.camera.width) == (517.3, 255.3, 640)
    seq = read_tum_rgbd(root, camera=data["camera"])
    assert seq.info["camera_source"] == "argument" and seq.camera.width == W


@pytest.mark.parametrize(
    ("file", "row", "message"),
    [
        ("rgb.txt", "1305031103.0 rgb/a.png extra", r"rgb.txt, line 9: expected"),
        ("depth.txt", "abc depth/a.png", r"depth.txt, line 9: timestamp 'abc'"),
        ("rgb.txt", "1.0 rgb/a.png", r"rgb.txt, line 9: .*not greater"),
        ("groundtruth.txt", "1305031103.0 1 2 3 0 0 0 0", r"groundtruth.txt, line 7: zero"),
    ],
)
def test_malformed_lists(tmp_path: Path, file: str, row: str, message: str):
    root = write(tmp_path / "seq", make_sequence())
    with (root / file).open("a") as handle:
        handle.write(row + "\n")
    with pytest.raises(ValueError, match=message):
        read_tum_rgbd(root)


@pytest.mark.parametrize("missing", ["rgb.txt", "depth.txt", "groundtruth.txt", "depth_png"])
def test_missing_files(tmp_path: Path, missing: str):
    root = write(tmp_path / "seq", make_sequence())
    target = sorted((root / "depth").iterdir())[1] if missing == "depth_png" else root / missing
    target.unlink()
    with pytest.raises(FileNotFoundError, match=target.name):
        read_tum_rgbd(root)
