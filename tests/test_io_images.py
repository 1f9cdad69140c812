"""RGB and depth PNG files: exact round trips, channel order, depth encoding, bad files."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.io.images import read_depth, read_rgb, write_depth, write_rgb


def test_rgb_round_trip_uint8_and_float(tmp_path: Path):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    write_rgb(tmp_path / "a.png", image)
    got = read_rgb(tmp_path / "a.png")
    assert got.shape == (3, 12, 16) and got.dtype == torch.float32
    expected = torch.from_numpy(image.transpose(2, 0, 1).astype(np.float32) / np.float32(255))
    assert torch.equal(got, expected)
    write_rgb(tmp_path / "b.png", got)
    assert torch.equal(read_rgb(tmp_path / "b.png"), got)
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()


def test_rgb_order_is_rgb_not_bgr(tmp_path: Path):
    image = torch.zeros(3, 2, 2)
    image[0] = 1.0  # pure red
    write_rgb(tmp_path / "red.png", image)
    raw = cv2.imread(str(tmp_path / "red.png"), cv2.IMREAD_UNCHANGED)
    assert (raw[..., 2] == 255).all() and (raw[..., :2] == 0).all()  # OpenCV stores BGR
    assert torch.equal(read_rgb(tmp_path / "red.png"), image)


def test_grey_image_is_expanded(tmp_path: Path):
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    cv2.imwrite(str(tmp_path / "grey.png"), grey)
    got = read_rgb(tmp_path / "grey.png")
    assert got.shape == (3, 3, 4)
    for c in range(3):
        assert torch.equal(got[c], torch.from_numpy(grey.astype(np.float32) / np.float32(255)))


def test_float_rgb_is_rounded_and_clamped(tmp_path: Path):
    image = torch.tensor([0.0, 0.5, 1.2, -0.1, 0.2, 0.999]).reshape(3, 1, 2)
    write_rgb(tmp_path / "a.png", image)
    got = (read_rgb(tmp_path / "a.png") * 255).round().to(torch.uint8).flatten().tolist()
    assert got == [0, 128, 255, 0, 51, 255]


def test_depth_round_trip(tmp_path: Path):
    depth = torch.tensor([[0.0, 1.0, 2.3456], [65.535, 65.6, float("inf")]])
    write_depth(tmp_path / "d.png", depth)
    raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    assert raw.tolist() == [[0, 1000, 2346], [65535, 0, 0]]
    got = read_depth(tmp_path / "d.png", 1000.0)
    assert got.shape == (1, 2, 3) and got.dtype == torch.float32
    expected = torch.tensor([[[0.0, 1.0, 2.346], [65.535, 0.0, 0.0]]])
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-6)
    millimetres = torch.randint(0, 65536, (1, 8, 9)).double() / 1000.0
    write_depth(tmp_path / "mm.png", millimetres)
    assert torch.equal(read_depth(tmp_path / "mm.png"), millimetres.float())


def test_depth_scale_5000(tmp_path: Path):
    write_depth(tmp_path / "d.png", np.full((2, 2), 1.2345), scale=5000.0)
    raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    assert (raw == 6172).all()  # round half to even
    torch.testing.assert_close(
        read_depth(tmp_path / "d.png", 5000.0), torch.full((1, 2, 2), 6172 / 5000.0)
    )


def test_bad_depth_input(tmp_path: Path):
    with pytest.raises(ValueError, match="NaN"):
        write_depth(tmp_path / "d.png", torch.tensor([[float("nan")]]))
    with pytest.raises(ValueError, match="negative"):
        write_depth(tmp_path / "d.png", torch.tensor([[-1.0]]))
    with pytest.raises(ShapeError):
        write_depth(tmp_path / "d.png", torch.zeros(2, 3, 4))
    with pytest.raises(ValueError, match="scale"):
        write_depth(tmp_path / "d.png", torch.zeros(2, 2), scale=0.0)
    assert not list(tmp_path.iterdir())


def test_bad_rgb_input(tmp_path: Path):
    with pytest.raises(ShapeError):
        write_rgb(tmp_path / "a.png", torch.zeros(4, 3, 3))
    with pytest.raises(ValueError, match="NaN"):
        write_rgb(tmp_path / "a.png", torch.full((3, 2, 2), float("nan")))
    with pytest.raises(ValueError, match="PNG"):
        write_rgb(tmp_path / "a.bmp", torch.zeros(3, 2, 2))


def test_corrupt_png_names_file(tmp_path: Path):
    write_rgb(tmp_path / "a.png", torch.rand(3, 8, 8))
    data = (tmp_path / "a.png").read_bytes()
    (tmp_path / "a.png").write_bytes(data[:20])
    with pytest.raises(ValueError, match=r"a\.png.*not a readable image"):
        read_rgb(tmp_path / "a.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(ValueError, match="empty.png"):
        read_depth(tmp_path / "empty.png")


def test_missing_file_and_wrong_kind(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="none.png"):
        read_rgb(tmp_path / "none.png")
    with pytest.raises(FileNotFoundError, match="none.png"):
        read_depth(tmp_path / "none.png")
    write_rgb(tmp_path / "rgb.png", torch.rand(3, 4, 4))
    with pytest.raises(ValueError, match="16-bit"):
        read_depth(tmp_path / "rgb.png")
