"""Hard (non-differentiable) splatting of surfel and point maps into pinhole cameras.

Three renderers share one z-buffer:

- :func:`render_surfel_index` draws oriented disks (surfels) and returns the global surfel
  index map of seed 1 Sec. III-A, with exact per-pixel depths and the surfel normals.
- :func:`render_points` draws square point splats (RGB-D, ids, mask) with the sizes of
  seed 2 Sec. III-D1: a fixed size, the inverse-depth size of Eq. 2, or the multi-pass scheme
  with a few fixed sizes merged by nearest depth.
- :func:`neighbour_surfels` lists the distinct surfel ids within each keypoint's radius (the
  neighbouring surfel set of seed 1); :func:`keypoint_disk_mask` gives the pixels it reads, so
  that only those are rendered.

Design notes:

- **Z-buffer.** A candidate (pixel, primitive) is an int64 key whose high 32 bits are the bits
  of its float32 depth (positive floats order like their bit patterns) and whose low 32 bits
  are the primitive index. ``scatter_reduce(..., reduce="amin")`` over the flattened pixels
  keeps, per pixel, the nearest depth and its id in one pass; equal depths go to the lower
  index, so renders are deterministic and independent of the input order. (Surfel keys hold
  the inverse depth and are max-reduced, see below.) Cameras are rendered one after the
  other; everything per camera is vectorised over primitives and pixels (chunked to bound the
  memory).
- **Surfels.** The ray through a pixel centre ``d = ((u - cx) / fx, (v - cy) / fy, 1)`` hits
  the plane of a surfel (centre ``c``, unit normal ``n``, radius ``r``, camera frame) at
  z-depth ``t = (n.c) / (n.d)``; the pixel is covered when ``|t d - c| <= r``. Multiplying by
  ``(n.d)^2`` makes the test a quadratic (conic) in the pixel coordinates and ``1 / t`` an
  affine function of them, so a chunk of same-sized candidate windows is evaluated with small
  matrix products. Candidate windows are the pixels of the analytic bounding box of the
  projected ellipse (clipped to the image), grouped in buckets of a few window sizes (sparse
  buckets merged into larger ones); a window starts at its box's top-left pixel (reaching
  into a padded z-buffer past the image border), so that a surfel's window, and every key it
  writes, is the same whatever else is drawn (masked renders skip the cells and surfels that
  reach no pixel to render). Surfels are first culled against the view frustum with
  their bounding spheres (one ``4 x 3`` product over the world-frame map) and the survivors
  numbered in map order. Their z-buffer key holds the float32 *inverse* depth (high word) and
  a tie-breaker decreasing with that number (low word), max-reduced: the matrix product writes
  the keys directly (the tie-breaker is a constant polynomial) and the ray-disk test is one
  ``copysign`` that makes misses negative. The nearest hit wins; equal inverse depths go to
  the lower index. Depths come out as ``1 / inverse depth``, bit for bit what a depth-keyed
  z-buffer would store, but two hits whose different inverse depths round to the same depth
  are ordered by the inverse depth rather than the index.
- **Points.** A point of integer size ``k`` covers the ``k x k`` pixels whose centres lie in
  the square of side ``k`` centred on its projection (OpenGL point rasterisation). The keys of
  each pass (size level) are scattered once into an "anchor" image (top-left pixel of each
  splat); the squares are filled with separable sliding-window minima, evaluated for all
  passes together from the largest size down, and the minimum merges the passes by nearest
  depth. The cost is one scatter per point plus a few image-sized operations per pass,
  independent of the splat area.
- **Bad input.** Wrong shapes, ``B = 0`` -> :class:`~diffloc.checks.ShapeError`; non-finite
  poses -> ``ValueError``. Map entries with any NaN or infinite coordinate (centre, normal,
  radius, point) are treated as missing and *culled*; finite but invalid values (radius
  ``<= 0``, zero normal) raise ``ValueError``. Primitives behind the camera (centre or point
  with ``z <= MIN_DEPTH``) are culled; an empty map gives an empty render.
- **Cameras.** ``camera`` is one :class:`PinholeCamera` (batch shape ``()``) shared by all
  poses or a batch of ``B`` cameras of one image size. Point splats are placed at the
  (distorted) projection, so distorted cameras work; the surfel renderer needs an ideal
  pinhole (``distortion=None``) because it intersects pixel rays analytically.
"""

from __future__ import annotations

import bisect
import functools
import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass

import torch

from diffloc.checks import ShapeError, check_finite, check_shape
from diffloc.geometry.camera import MIN_DEPTH, PinholeCamera
from diffloc.geometry.se3 import invert

__all__ = [
    "PointRender",
    "KeypointDisks",
    "PointSizes",
    "SurfelIndexRenderer",
    "SurfelRender",
    "keypoint_disk_mask",
    "neighbour_surfels",
    "render_points",
    "render_surfel_index",
    "see_through_fraction",
]

_EMPTY_KEY = torch.iinfo(torch.int64).max
_LOW32 = 0xFFFFFFFF
_MAX_PRIMITIVES = 2**31 - 1
_CHUNK = 1 << 18
"""Elements per chunk of vectorised work: bounds temporaries to a few MB each."""
_GRAZING_COS = 1e-6
"""Surfels seen exactly edge-on (|cos| of the view angle below this) cover no pixel centre."""
_BBOX_MARGIN_PX = 1e-2
"""Slack added to the analytic ellipse bounding box against float32 rounding."""
_PREFILTER_MARGIN_PX = 0.05
"""Slack of the disk-box test of masked renders: far above the float32 rounding of a pixel
coordinate (~1e-4 px) and of the ray-disk test (~1e-6 of the disk)."""
_ELLIPSE_CONDITION = 1e-3
"""Ellipses with ``4AC - B^2 <= 1e-3 * 4AC`` (aspect ratio above ~30) use the sphere bound."""
_CULL_SLACK = 1e-5
"""Slack of the frustum cull against float32 rounding, relative to ``1 m + |camera centre|``."""
_HIGH_WORD = 1 if sys.byteorder == "little" else 0
"""Which of the two 32-bit words of an int64 in memory holds its high half."""
_NO_KEY = torch.iinfo(torch.int64).min
"""Surfel z-buffer key of an empty pixel (keys are max-reduced)."""
_TIE_TOP = 0x7F7FFFFF
"""Bits of the largest finite float32; tie-breakers count down from it."""
_MAX_SURFELS = _TIE_TOP - 0x00800000 + 1
"""Surfels per render, so that every tie-breaker is a positive normal float32."""
_SURFEL_CHUNK = 1 << 16
"""Surfels per chunk of the box test of masked renders (temporaries stay in the CPU caches)."""
_MERGE_PIXELS = 4096
"""A bucket of windows joins a larger one when that adds at most this many candidate pixels
(about the cost of the few tensor operations that every bucket takes)."""
_PAD_STEP = 32
"""The z-buffer row padding is a multiple of this (few distinct strides for the basis cache)."""
_GEMM_COLUMNS = 12
"""Fewest windows per matrix product of :func:`_rasterise_surfels`: from 12 columns on, the
CPU sgemm (MKL, AVX2) rounds every output column alike, whatever the other columns; narrower
products take other kernels whose roundings differ."""
_BASIS_CACHE_AREA = 1024
"""Window bases up to this many pixels are memoised (a few MB at most)."""
_PROBE_DIRECTION = (1.0, 0.7548776662466927, 0.5698402909980532)
"""A direction orthogonal to no simple normal (powers of the inverse plastic number)."""


# ---------------------------------------------------------------------------- results


@dataclass(frozen=True)
class SurfelRender:
    """Surfel index map of a batch of cameras.

    Attributes:
        ids: (B, H, W) int64 index of the visible surfel, -1 where none.
        depth: (B, H, W) float32 z-depth (metres) of the ray-disk hit, 0 where none.
        normals: (B, 3, H, W) float32 unit normal of the visible surfel in the *camera* frame
            (as stored in the map, not flipped towards the camera), 0 where none.
    """

    ids: torch.Tensor
    depth: torch.Tensor
    normals: torch.Tensor

    @property
    def mask(self) -> torch.Tensor:
        """(B, H, W) bool, true where a surfel is visible."""
        return self.ids >= 0


@dataclass(frozen=True)
class PointRender:
    """RGB-D render of a point map.

    Attributes:
        rgb: (B, 3, H, W) float32 colour of the visible point, 0 where none.
        depth: (B, 1, H, W) float32 z-depth (metres), 0 where none.
        ids: (B, H, W) int64 index of the visible point, -1 where none.
        mask: (B, 1, H, W) bool, true where a point is visible.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    ids: torch.Tensor
    mask: torch.Tensor


@dataclass(frozen=True)
class PointSizes:
    """Screen-space splat sizes (side of the square, in pixels) for :func:`render_points`.

    Each point first gets the inverse-depth size of seed 2 Eq. 2,
    ``rho = clamp(rho_max / z, rho_min, rho_max)`` (``z`` in metres, so ``rho_max`` is the
    size at 1 m and closer). It is then snapped to the nearest of the integer ``levels``
    (ties round up); points of one level form one rendering pass and passes are merged by
    nearest depth (seed 2 Fig. 5). ``levels=None`` uses every integer in
    ``[round(rho_min), round(rho_max)]`` (at least 1), which renders Eq. 2 per point with the
    size rounded to whole pixels as OpenGL does. A fixed size ``k`` is ``levels=(k,)``.

    Attributes:
        rho_min: smallest size (pixels, > 0).
        rho_max: largest size (pixels, >= rho_min).
        levels: optional sorted tuple of distinct positive integer sizes, the passes.

    Raises:
        ValueError: non-finite or non-positive sizes, ``rho_max < rho_min``, bad levels.

    Example:
        >>> PointSizes.inverse_depth(1.0, 4.0).pass_sizes()
        (1, 2, 3, 4)
        >>> PointSizes.fixed(2).pass_sizes()
        (2,)
    """

    rho_min: float = 1.0
    rho_max: float = 1.0
    levels: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("rho_min", "rho_max"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"PointSizes.{name} must be a positive number, got {value!r}")
        if self.rho_max < self.rho_min:
            raise ValueError(f"PointSizes.rho_max ({self.rho_max}) < rho_min ({self.rho_min})")
        if self.levels is not None:
            levels = tuple(self.levels)
            valid = all(isinstance(k, int) and not isinstance(k, bool) and k > 0 for k in levels)
            if not levels or not valid or list(levels) != sorted(set(levels)):
                raise ValueError(
                    f"PointSizes.levels must be increasing positive integers, got {self.levels!r}"
                )
            object.__setattr__(self, "levels", levels)

    @classmethod
    def fixed(cls, size: int) -> PointSizes:
        """Every point drawn as a ``size x size`` square (a single pass)."""
        return cls(rho_min=float(size), rho_max=float(size), levels=(size,))

    @classmethod
    def inverse_depth(cls, rho_min: float, rho_max: float) -> PointSizes:
        """Eq. 2 per point, rounded to whole pixels."""
        return cls(rho_min=rho_min, rho_max=rho_max)

    @classmethod
    def multi_pass(cls, rho_min: float, rho_max: float, levels: tuple[int, ...]) -> PointSizes:
        """Eq. 2 snapped to a few fixed sizes, one pass each, merged by nearest depth."""
        return cls(rho_min=rho_min, rho_max=rho_max, levels=levels)

    def pass_sizes(self) -> tuple[int, ...]:
        """The integer splat sizes, one rendering pass each."""
        if self.levels is not None:
            return self.levels
        low = max(1, math.floor(self.rho_min + 0.5))
        return tuple(range(low, max(low, math.floor(self.rho_max + 0.5)) + 1))

    def level_index(self, depth: torch.Tensor) -> torch.Tensor:
        """Pass index of points at camera-frame z-depths ``depth`` (any shape, > 0).

        Args:
            depth: (...) z-depths in metres.

        Returns:
            (...) int64 indices into :meth:`pass_sizes`.
        """
        sizes = self.pass_sizes()
        rho = (self.rho_max / depth).clamp(self.rho_min, self.rho_max)
        midpoints = torch.tensor(
            [0.5 * (a + b) for a, b in zip(sizes[:-1], sizes[1:], strict=True)],
            dtype=rho.dtype,
            device=rho.device,
        )
        return torch.bucketize(rho, midpoints, right=True)


# ---------------------------------------------------------------------------- validation


def _check_poses(T_wc: torch.Tensor) -> int:
    """Validate (B, 4, 4) poses and return B."""
    check_shape(T_wc, "B,4,4", "T_wc")
    if T_wc.shape[0] == 0:
        raise ShapeError("T_wc must hold at least one pose, got shape (0, 4, 4)")
    check_finite(T_wc, "T_wc")
    return T_wc.shape[0]


def _check_camera(camera: PinholeCamera, batch: int) -> PinholeCamera:
    """A float32 copy of ``camera``, which must be one camera or a batch of ``batch``."""
    if not isinstance(camera, PinholeCamera):
        raise TypeError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
    if tuple(camera.batch_shape) not in ((), (batch,)):
        raise ShapeError(
            f"camera batch shape must be () or ({batch},) to match T_wc, "
            f"got {tuple(camera.batch_shape)}"
        )
    return camera.to(torch.float32)


def _check_map_size(n: int, what: str, limit: int = _MAX_PRIMITIVES) -> None:
    if n > limit:
        raise ValueError(f"at most {limit} {what} can be rendered, got {n}")


@dataclass(frozen=True)
class _View:
    """One camera of a batch: world-to-camera transform and intrinsics."""

    R_cw: torch.Tensor  # (3, 3) float32
    t_cw: torch.Tensor  # (3, 1) float32
    fx: float
    fy: float
    cx: float
    cy: float
    camera: PinholeCamera  # unbatched, for the distortion model

    def to_camera(self, points_world_t: torch.Tensor, elementwise: bool = False) -> torch.Tensor:
        """(3, n) camera-frame coordinates of (3, n) world points (coordinates as rows).

        Pass ``points_world.T`` for (n, 3) points: the transposed view needs no copy. One
        matrix product by default; ``elementwise`` (:func:`_rigid_columns`, about 4x slower)
        rounds every point alike whatever n, as renders of subsets of a map need.
        """
        if elementwise:
            return _rigid_columns(self.R_cw, points_world_t, self.t_cw)
        return torch.addmm(self.t_cw, self.R_cw, points_world_t)


def _views(T_wc: torch.Tensor, camera: PinholeCamera) -> Iterator[_View]:
    """Yield the cameras of a validated batch one at a time."""
    T_cw = invert(T_wc.to(torch.float64)).to(torch.float32)
    batch = T_wc.shape[0]
    params = torch.stack((camera.fx, camera.fy, camera.cx, camera.cy), dim=-1).expand(batch, 4)
    for b, (fx, fy, cx, cy) in enumerate(params.tolist()):
        single = camera if len(camera.batch_shape) == 0 else camera[b]
        yield _View(T_cw[b, :3, :3], T_cw[b, :3, 3:], fx, fy, cx, cy, single)


# ---------------------------------------------------------------------------- z-buffer keys


def _pack_keys(depth: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """int64 keys ordering by float32 ``depth > 0`` first, then by ``ids`` in [0, 2^31)."""
    bits = depth.to(torch.float32).contiguous().view(torch.int32).to(torch.int64)
    return torch.add(ids, bits, alpha=1 << 32)


def _unpack_keys(keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(ids, depth)`` of z-buffer keys: -1 and 0 where the key is empty."""
    empty = keys == _EMPTY_KEY
    ids = torch.bitwise_and(keys, _LOW32).masked_fill_(empty, -1)
    depth_bits = torch.bitwise_right_shift(keys, 32).to(torch.int32)
    depth = depth_bits.view(torch.float32).masked_fill_(empty, 0.0)
    return ids, depth


def _key_words(keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(low, high)`` int32 halves of (P,) int64 keys, (P,) strided views each (no copy)."""
    words = keys.view(torch.int32)  # (2 P,)
    return words[1 - _HIGH_WORD :: 2], words[_HIGH_WORD::2]


def _empty_keys(shape: tuple[int, ...], device: torch.device) -> torch.Tensor:
    return torch.full(shape, _EMPTY_KEY, dtype=torch.int64, device=device)


def _gather_channels_first(values: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) rows of (N, C) ``values`` picked by (B, H, W) ``ids`` (-1 reads row 0)."""
    channels = values.shape[1]
    batch, height, width = ids.shape
    offsets = torch.arange(channels, device=ids.device).view(1, channels, 1, 1)
    flat = ids.clamp_min(0)[:, None] * channels + offsets
    if values.numel() == 0:
        return torch.zeros(flat.shape, dtype=values.dtype, device=values.device)
    return values.reshape(-1).index_select(0, flat.view(-1)).view(flat.shape)


# ---------------------------------------------------------------------------- surfels


@dataclass(frozen=True)
class _SurfelCandidates:
    """The surfels of one camera that pass the frustum cull (and, in a masked render, the box
    test), in the camera frame.

    They may come in any order: the z-buffer breaks ties with the map index, not the position.
    """

    ids: torch.Tensor  # (M,) int64 distinct map indices
    centers: torch.Tensor  # (3, M) float32 camera-frame centres (coordinates as rows)
    normals: torch.Tensor  # (3, M) float32 unit camera-frame normals
    radii: torch.Tensor  # (M,) float32


@dataclass(frozen=True)
class _Windows:
    """Candidate pixel windows of one camera, sorted into buckets of one window size.

    Window ``w`` tests the ``size_v x size_u`` pixels from flat index ``base[w]`` of a
    z-buffer of ``buffer_rows x stride`` pixels (the image, padded right and below so that every
    window fits from the top-left pixel of its surfel's box), with
    polynomials in the offsets ``(i, j)`` from that top-left pixel: ``inside[:, w]`` holds the
    coefficients of ``1 - q`` (>= 0 on the disk, see :class:`_Conics`) on the monomials
    ``(i^2, i j, j^2, i, j, 1)``, ``keys[:, 2 w + 1]`` those of the inverse depth on
    ``(i, j, 1)`` and ``keys[:, 2 w]`` a constant, the float32 whose bits are the window's
    z-buffer tie-breaker (see :func:`_rasterise_surfels`; the two swap on big-endian
    machines, so that each pair reads as one int64 key). Windows ``start .. start + count - 1``
    of a bucket share the size; ``near`` buckets hold surfels that may reach the near plane.
    """

    inside: torch.Tensor  # (6, K) float32
    keys: torch.Tensor  # (3, 2 K) float32
    base: torch.Tensor  # (K,) int64 flat index of the top-left pixel
    buckets: list[tuple[int, int, bool, int, int]]  # size_u, size_v, near, start, count
    stride: int  # z-buffer row length, >= W
    buffer_rows: int  # z-buffer rows, >= H


def _frustum_planes(view: _View, height: int, width: int) -> tuple[list[list[float]], float]:
    """Camera-frame unit normals of the four side planes of the frustum, and the cull slack.

    The planes pass through the camera centre and the outer pixel edges (e.g. ``u = -0.5``,
    ``fx x + (cx + 0.5) z >= 0``); every disk point seen at a pixel centre lies strictly inside
    all four half-spaces, which only meet in front of the camera. The slack (metres) absorbs the
    float32 rounding of the distances.

    Returns:
        ``(planes, slack)``: four ``[a, b, c]`` normals pointing inwards and the slack.
    """
    planes = []
    for a, b, axis in (
        (view.fx, view.cx + 0.5, 0),
        (-view.fx, width - 0.5 - view.cx, 0),
        (view.fy, view.cy + 0.5, 1),
        (-view.fy, height - 0.5 - view.cy, 1),
    ):
        norm = math.hypot(a, b)
        normal = [0.0, 0.0, b / norm]
        normal[axis] = a / norm
        planes.append(normal)
    return planes, _CULL_SLACK * (1.0 + float(view.t_cw.norm()))


def _frustum_candidates(
    centers: torch.Tensor, radii: torch.Tensor, view: _View, height: int, width: int
) -> torch.Tensor:
    """(M,) int64 increasing indices of the surfels whose bounding sphere may be in view.

    One ``(4, 3) x (3, N)`` product gives, straight from the world-frame centres, the signed
    distances to the four side planes of :func:`_frustum_planes`; a surfel is kept when its
    radius (plus the slack) reaches into all four half-spaces. This also drops the surfels
    behind the camera; the centre's ``z > MIN_DEPTH`` is tested on the survivors. Surfels with
    NaN coordinates or radii are dropped.

    Args:
        centers: (N, 3) world-frame centres.
        radii: (N,) radii.
        view: the camera.
        height: image height.
        width: image width.

    Returns:
        (M,) int64 surfel indices, increasing.
    """
    planes, slack = _frustum_planes(view, height, width)
    normals = torch.tensor(planes, dtype=torch.float32, device=centers.device)  # (4, 3)
    distances = torch.addmm(normals @ view.t_cw, normals @ view.R_cw, centers.T)  # (4, N)
    reach = distances.amin(0).add_(radii)
    return (reach >= -slack).nonzero().view(-1)


def _concat_ranges(starts: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """(sum counts,) int64 concatenation of the ranges ``starts[i] + (0 .. counts[i] - 1)``."""
    offsets = torch.cumsum(counts, 0).sub_(counts)
    shift = torch.repeat_interleave(starts - offsets, counts)
    return torch.arange(shift.shape[0], device=starts.device).add_(shift)


def _cell_keys(cells: torch.Tensor) -> torch.Tensor:
    """(N,) int64 keys, equal exactly for equal rows, of (N, 3) int64 cell coordinates."""
    if cells.shape[0] == 0:
        return cells[:, 0]
    cells = cells - cells.amin(0)
    extent = cells.amax(0).add_(1).tolist()
    if extent[0] * extent[1] * extent[2] < 2**62:
        return (cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]
    return torch.unique(cells, dim=0, return_inverse=True)[1]  # slower, no overflow


@dataclass(frozen=True)
class _SurfelCells:
    """The finite surfels of a map grouped by cubic cells, for frustum culling by cell.

    Cell ``g`` holds the surfels ``ids[starts[g] : starts[g + 1]]`` (increasing map indices),
    whose data are stored cell by cell in ``centers``, ``normals``, ``radii`` and ``extents``;
    its bounding sphere (float64, slightly inflated) holds all their bounding spheres, and its
    box (``box_centres +- box_extents``) all their disks' axis-aligned boxes.
    """

    ids: torch.Tensor  # (N',) int64 map indices, cell by cell
    centers: torch.Tensor  # (N', 3) float32
    normals: torch.Tensor  # (N', 3) float32
    radii: torch.Tensor  # (N',) float32
    extents: torch.Tensor  # (N', 3) float32 half-extents of the disks (:func:`_disk_extents`)
    starts: torch.Tensor  # (G + 1,) int64
    sphere_centres: torch.Tensor  # (G, 3) float64
    sphere_radii: torch.Tensor  # (G,) float64
    box_centres: torch.Tensor  # (G, 3) float64
    box_extents: torch.Tensor  # (G, 3) float64

    @classmethod
    def build(
        cls, centers: torch.Tensor, normals: torch.Tensor, radii: torch.Tensor, size: float
    ) -> _SurfelCells:
        """Group the finite surfels of (N, 3) ``centers``, ``normals``, (N,) ``radii`` by cells of
        ``size`` metres. Non-finite surfels are never drawn and are left out."""
        finite = torch.isfinite(centers).all(1) & torch.isfinite(normals).all(1)
        ids = (finite & torch.isfinite(radii)).nonzero().view(-1)
        cells = torch.floor(centers.index_select(0, ids).double() / size).long()
        _, cell, counts = torch.unique(_cell_keys(cells), return_inverse=True, return_counts=True)
        ids = ids.index_select(0, torch.sort(cell, stable=True).indices)
        starts = torch.cat((counts.new_zeros(1), torch.cumsum(counts, 0)))
        cell = torch.repeat_interleave(torch.arange(counts.shape[0], device=ids.device), counts)
        c = centers.index_select(0, ids).double()
        mean = torch.zeros(counts.shape[0], 3, dtype=torch.float64, device=ids.device)
        mean = mean.index_add_(0, cell, c).div_(counts[:, None])
        reach = (c - mean.index_select(0, cell)).norm(dim=1).add_(radii.index_select(0, ids))
        bound = torch.zeros_like(counts, dtype=torch.float64).scatter_reduce_(
            0, cell, reach, "amax"
        )
        radii, normals = radii.index_select(0, ids), normals.index_select(0, ids)
        extents = _disk_extents(normals, radii)
        corners = (c - extents.double(), c + extents.double())
        index = cell[:, None].expand(-1, 3)
        low = torch.full_like(mean, math.inf).scatter_reduce_(0, index, corners[0], "amin")
        high = torch.full_like(mean, -math.inf).scatter_reduce_(0, index, corners[1], "amax")
        return cls(
            ids,
            centers.index_select(0, ids),
            normals,
            radii,
            extents,
            starts,
            mean,
            bound.mul_(1.0 + 1e-6).add_(1e-6),
            (low + high) / 2,
            (high - low) / 2,
        )

    def cull(
        self, view: _View, height: int, width: int, pixel_sums: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(M,) int64 positions (into the cell-ordered data) of the surfels that may be in view.

        Cells whose bounding sphere is inside all four frustum half-spaces (with a margin far
        above the float32 rounding of :func:`_frustum_candidates`) keep all their surfels,
        cells outside one of them none; the surfels of the others are tested one by one by
        :func:`_frustum_candidates`. The result is the set that it would select on the whole
        map. With ``pixel_sums`` (see :func:`_summed_area`), the cells whose box can reach no
        pixel to render (:meth:`_reach`) are dropped first.
        """
        planes, slack = _frustum_planes(view, height, width)
        planes = torch.tensor(planes, dtype=torch.float64, device=self.starts.device)
        R, t = view.R_cw.double(), view.t_cw.double()
        distances = torch.addmm((planes @ t).T, self.sphere_centres, (planes @ R).T)  # (G, 4)
        nearest = distances.amin(1)
        margin = 100.0 * slack
        inside = nearest - self.sphere_radii >= margin - slack
        cells = torch.nonzero(inside | (nearest + self.sphere_radii >= -slack - margin)).view(-1)
        inside = inside.index_select(0, cells)
        if pixel_sums is not None:
            reach = self._reach(cells, view, slack, pixel_sums)
            cells, inside = cells[reach], inside[reach]
        starts = self.starts.index_select(0, cells)
        counts = self.starts.diff().index_select(0, cells)
        kept = _concat_ranges(starts[inside], counts[inside])
        tested = _concat_ranges(starts[~inside], counts[~inside])
        centers, radii = self.centers.index_select(0, tested), self.radii.index_select(0, tested)
        near = tested.index_select(0, _frustum_candidates(centers, radii, view, height, width))
        return torch.cat((kept, near))

    def _reach(
        self, cells: torch.Tensor, view: _View, slack: float, pixel_sums: torch.Tensor
    ) -> torch.Tensor:
        """(C,) bool: the (C,) ``cells`` whose box may reach a pixel of ``pixel_sums``
        (:func:`_box_touches`; camera-frame boxes that hold the world-frame ones, grown by 1 mm
        plus 100 times the frustum ``slack`` against the float32 rounding of the surfels'
        camera-frame coordinates)."""
        R = view.R_cw.double()
        centres = torch.addmm(view.t_cw.double(), R, self.box_centres.index_select(0, cells).T)
        extents = (R.abs() @ self.box_extents.index_select(0, cells).T).add_(1e-3 + 100 * slack)
        return _box_touches(centres.float(), extents.float(), view, pixel_sums)


def _rigid_columns(R: torch.Tensor, x: torch.Tensor, t: torch.Tensor | None = None) -> torch.Tensor:
    """``R x + t`` for (3, M) columns ``x``, elementwise: every column rounds alike whatever M.

    A matrix product picks its kernel by the number of columns, and its roundings with it
    (``(3, 3) x (3, M)`` products differ in the last bit between M = 10^4 and M = 10^5); the
    renderer draws varying subsets of a map (frustum, masks) and needs each surfel bit for bit
    alike in all of them.

    Args:
        R: (3, 3) rotation.
        x: (3, M) columns.
        t: (3, 1) translation, or ``None``.
    """
    out = R[:, :1] * x[:1] if t is None else torch.addcmul(t, R[:, :1], x[:1])
    return out.addcmul_(R[:, 1:2], x[1:2]).addcmul_(R[:, 2:], x[2:])


def _disk_extents(normals: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """(N, 3) half-extents ``r sqrt(1 - n_i^2)`` of the axis-aligned boxes of disks with
    (N, 3) normals (any non-zero length; NaN for non-finite ones) and (N,) radii."""
    unit = normals / normals.norm(dim=1, keepdim=True)
    return torch.rsub(unit * unit, 1.0).clamp_(min=0.0).sqrt_().mul_(radii[:, None])


@dataclass(frozen=True)
class _Conics:
    """Ray-disk conics of M surfels; ``(2, M)`` fields hold a ``u`` row and a ``v`` row.

    ``q(du, dv) = du (A du + B dv + D) + dv (C dv + E) <= 1`` is the ray-disk test in pixel
    offsets ``(du, dv)`` from the projected centre, and the inverse hit depth is
    ``g0 + gu du + gv dv``.
    """

    AC: torch.Tensor  # (2, M) A, C
    B: torch.Tensor  # (M,)
    DE: torch.Tensor  # (2, M) D, E
    g0: torch.Tensor  # (M,)
    g_uv: torch.Tensor  # (2, M) gu, gv
    centre: torch.Tensor  # (2, M) projected centre (u, v), pixels

    def select(self, index: torch.Tensor) -> _Conics:
        """The conics of the (K,) surfels ``index``."""
        return _Conics(*(field.index_select(-1, index) for field in vars(self).values()))


def _surfel_conics(
    c: torch.Tensor, n: torch.Tensor, r: torch.Tensor, view: _View
) -> tuple[_Conics, torch.Tensor, torch.Tensor]:
    """Ray-disk conics of surfels in front of the camera.

    The ray ``d = c / cz + (du / fx, dv / fy, 0)`` meets the plane ``n.p = k`` (``k = n.c``)
    at ``t = k / (n.d)``, and ``|t d - c| <= r`` is ``|k e - (n_x a + n_y b) c|^2 <=
    r^2 (n.d)^2`` with ``e = (a, b, 0)``, ``a = du / fx``, ``b = dv / fy``. Expanding with
    ``h = cz / k`` and ``m = |c|^2 - r^2`` and dividing by ``r^2 (k / cz)^2`` gives
    ``A = h^2 (k^2 - 2 k n_x c_x + n_x^2 m) / (r f_x)^2``,
    ``B = 2 h^2 (n_x n_y m - k (n_y c_x + n_x c_y)) / (r^2 f_x f_y)``, ``C`` like ``A``,
    ``D = -2 n_x h / f_x``, ``E = -2 n_y h / f_y``; ``1 / t = 1 / cz + n_x a / k + n_y b / k``.

    Args:
        c: (3, M) centres, camera frame, ``cz > 0``.
        n: (3, M) unit normals, camera frame.
        r: (M,) radii.
        view: the camera.

    Returns:
        ``(conics, k, cc)`` with (M,) ``k = n.c`` and ``cc = |c|^2``.
    """
    cc = (c * c).sum(0)
    cxy, cz, nxy = c[:2], c[2], n[:2]
    fx, fy = view.fx, view.fy
    f = c.new_tensor([[fx], [fy]])
    k = (n * c).sum(0)
    h = cz / k
    t = (h / r).square_()
    m = cc - r * r
    kn = k * nxy  # k n_x, k n_y
    AC = (
        (k * k - 2.0 * kn * cxy)
        .addcmul_(nxy * nxy, m)
        .mul_(t / c.new_tensor([[fx * fx], [fy * fy]]))
    )
    B = (nxy[0] * nxy[1] * m).sub_(kn[1] * cxy[0]).sub_(kn[0] * cxy[1]).mul_(t * (2.0 / (fx * fy)))
    DE = nxy * h * c.new_tensor([[-2.0 / fx], [-2.0 / fy]])
    g0 = cz.reciprocal()
    centre = (cxy * g0 * f).add_(c.new_tensor([[view.cx], [view.cy]]))
    return _Conics(AC, B, DE, g0, nxy / k / f, centre), k, cc


def _surfel_windows(
    surfels: _SurfelCandidates,
    view: _View,
    height: int,
    width: int,
    cull_backfaces: bool,
    pixel_sums: torch.Tensor | None = None,
) -> _Windows:
    """Conics and candidate windows of the surfels that may be visible in one camera.

    Args:
        surfels: the frustum-culled surfels.
        view: the camera.
        height: image height.
        width: image width.
        cull_backfaces: drop surfels whose normal points away from the camera.
        pixel_sums: summed-area table of the pixels to render (see :func:`_summed_area`), or
            ``None`` for all pixels.
    """
    layout = _bucket_layout(width, height, surfels.radii.device)
    lo, group, conics = _surfel_groups(surfels, view, layout, cull_backfaces, pixel_sums)
    return _bucket_windows(surfels, layout, lo, group, conics)


def _box_touches(
    centres: torch.Tensor, extents: torch.Tensor, view: _View, pixel_sums: torch.Tensor
) -> torch.Tensor:
    """(m,) bool: the camera-frame boxes ``centres +- extents`` ((3, m) each) that may be seen
    at a pixel of ``pixel_sums``.

    The ``u = fx x / z + cx`` of a box's points lies between the extremes of ``x / z`` over
    its ``x`` and ``z`` ranges (at its corners); only the pixel centres in that range, widened
    by :data:`_PREFILTER_MARGIN_PX` against rounding, can see the box. Boxes reaching the near
    plane (or with NaN entries) may be seen anywhere.
    """
    z_near, z_far = centres[2] - extents[2], centres[2] + extents[2]
    low, high = centres[:2] - extents[:2], centres[:2] + extents[:2]
    low.div_(torch.where(low < 0, z_near, z_far))  # smallest x / z, y / z
    high.div_(torch.where(high < 0, z_far, z_near))
    unbounded = (z_near > MIN_DEPTH).logical_not_()
    low.masked_fill_(unbounded, -math.inf)
    high.masked_fill_(unbounded, math.inf)
    width, height = view.camera.width, view.camera.height
    for row, f, principal, size in ((0, view.fx, view.cx, width), (1, view.fy, view.cy, height)):
        low[row].mul_(f).add_(principal - _PREFILTER_MARGIN_PX).ceil_().clamp_(0, size)
        high[row].mul_(f).add_(principal + _PREFILTER_MARGIN_PX).floor_().clamp_(-1, size - 1)
    return _box_sums(pixel_sums, low.to(torch.int32), high.to(torch.int32), width) > 0


def _surfel_groups(
    surfels: _SurfelCandidates,
    view: _View,
    layout: _BucketLayout,
    cull_backfaces: bool,
    pixel_sums: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor, _Conics]:
    """Boxes and buckets of M surfels.

    Args:
        surfels: the frustum-culled surfels.
        view: the camera.
        layout: the image's window buckets.
        cull_backfaces: drop surfels whose normal points away from the camera.
        pixel_sums: summed-area table of the pixels to render (see :func:`_summed_area`), or
            ``None`` for all pixels.

    Returns:
        ``(lo, group, conics)``: (2, M) int32 top-left box corners ``(u, v)`` (see
        :func:`_surfel_boxes`), (M,) int32 bucket before merging (:class:`_BucketLayout`),
        ``len(layout.shapes)`` for the surfels not drawn (not visible, or their box holds no
        pixel of ``pixel_sums``), and the surfels' conics.
    """
    c, n, r = surfels.centers, surfels.normals, surfels.radii
    conics, k, cc = _surfel_conics(c, n, r, view)
    total = c.sum(0) + n.sum(0) + r
    visible = (total - total) == 0  # false for NaN / inf
    visible &= c[2] > MIN_DEPTH
    visible &= k.square() > _GRAZING_COS**2 * cc
    if cull_backfaces:
        visible &= k < 0
    near = c[2] - r <= MIN_DEPTH
    lo, hi = _surfel_boxes(conics, near, r, c, view, layout.height, layout.width)
    extent = hi - lo + 1
    visible &= torch.minimum(*extent) > 0  # (integer amin is slow on CPU)
    level = layout.level.index_select(0, extent.clamp_(0, layout.level.shape[0] - 1).view(-1))
    level = level.view(2, -1)  # (2, m)
    group = level[0].mul_(layout.levels).add_(level[1]).mul_(2).add_(near)
    if pixel_sums is not None:
        visible &= _box_sums(pixel_sums, lo, hi, layout.width) > 0
    return lo, group.masked_fill_(~visible, len(layout.shapes)), conics


def _ellipse_box_offsets(conics: _Conics) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounding box ``(lo, hi)``, (2, M) offsets ``(du, dv)``, of ``q(du, dv) <= 1``.

    At the extremes of ``du`` the gradient of ``q`` is along ``du`` (``dq/ddv = 0``), which
    leaves the quadratic ``a du^2 + b du - c = 0`` with ``a = 4AC - B^2`` (> 0 for an ellipse),
    ``b = 4CD - 2BE``, ``c = E^2 + 4C``; the same for ``dv`` with the roles swapped. Where
    ``a`` is not positive or loses most of its digits to cancellation (very thin ellipses, a
    relative tolerance of :data:`_ELLIPSE_CONDITION`) the offsets are NaN.
    """
    A, C = conics.AC
    B = conics.B
    ac4 = 4.0 * A * C
    a = ac4 - B * B
    a = a.masked_fill_(a <= _ELLIPSE_CONDITION * ac4.abs(), math.nan)
    CA, ED = conics.AC.flip(0), conics.DE.flip(0)
    b = (4.0 * CA * conics.DE).sub_(2.0 * B * ED)
    root = (ED * ED + 4.0 * CA).mul_(4.0 * a).addcmul_(b, b).sqrt_()
    half_inv_a = 0.5 / a
    return (-b - root).mul_(half_inv_a), (root - b).mul_(half_inv_a)


def _surfel_boxes(
    conics: _Conics,
    near: torch.Tensor,
    r: torch.Tensor,
    c: torch.Tensor,
    view: _View,
    height: int,
    width: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(2, M) int32 inclusive pixel box corners ``lo = (u_lo, v_lo)``, ``hi``, in the image.

    The box is the analytic bounding box of the projected ellipse, intersected with the
    projection bound of the surfel's bounding sphere ``f r sqrt(x^2 + z^2) / (z (z - r))``
    (the only bound for ill-conditioned ellipses). A disk reaching the camera plane projects
    to an unbounded conic and gets the whole image. Empty boxes have ``lo > hi``.
    """
    lo, hi = _ellipse_box_offsets(conics)
    cxy, cz = c[:2], c[2]
    scale = r / (cz * (cz - r)).masked_fill_(near, 0.0)  # inf where near
    half = (
        (cxy * cxy).addcmul_(cz, cz).sqrt_().mul_(scale).mul_(c.new_tensor([[view.fx], [view.fy]]))
    )
    size = c.new_tensor([[width], [height]])
    # fmax / fmin skip the NaN offsets of ill-conditioned or unbounded conics.
    lo = torch.fmax(lo, -half).add_(conics.centre).sub_(_BBOX_MARGIN_PX).ceil_()
    hi = torch.fmin(hi, half).add_(conics.centre).add_(_BBOX_MARGIN_PX).floor_()
    lo = torch.clamp(lo, torch.zeros_like(size), size)
    hi = torch.clamp(hi, torch.full_like(size, -1.0), size - 1)
    return lo.to(torch.int32), hi.to(torch.int32)


def _bucket_sizes(limit: int) -> list[int]:
    """Window sizes used as buckets: 1, 2, 3, 4, 6, 8, then steps of ~40 %, last >= ``limit``."""
    sizes = [1, 2, 3, 4, 6, 8]
    while sizes[-1] < limit:
        sizes.append(math.ceil(sizes[-1] * 1.4))
    return sizes


@dataclass(frozen=True)
class _BucketLayout:
    """The window buckets of one image size.

    Bucket (group) ``g = 2 (levels l_u + l_v) + near`` holds windows of
    ``shapes[g] = (size_u, size_v)`` pixels, the :func:`_bucket_sizes` of levels ``l_u`` and
    ``l_v`` clipped to the image; ``near`` marks surfels that may reach the near plane.
    """

    width: int  # image width W
    height: int  # image height H
    levels: int
    shapes: tuple[tuple[int, int], ...]  # (G,)
    level: torch.Tensor  # (max(W, H) + 1,) int32 level of a box extent
    sizes: torch.Tensor  # (2, G + 1) int32 (size_u, size_v) of each group, then 1 (dropped)


@functools.lru_cache(maxsize=16)
def _bucket_layout(width: int, height: int, device: torch.device) -> _BucketLayout:
    """:class:`_BucketLayout` of a ``width x height`` image (memoised read-only constants)."""
    limit = max(width, height)
    sizes = _bucket_sizes(limit)
    levels = len(sizes)
    shapes = tuple(
        (min(sizes[g // (2 * levels)], width), min(sizes[g // 2 % levels], height))
        for g in range(2 * levels**2)
    )
    table = torch.tensor(sizes, device=device)
    level = torch.bucketize(torch.arange(limit + 1, device=device), table, out_int32=True)
    sizes = torch.tensor([*shapes, (1, 1)], dtype=torch.int32, device=device).T.contiguous()
    return _BucketLayout(width, height, levels, shapes, level, sizes)


def _bucket_windows(
    surfels: _SurfelCandidates,
    layout: _BucketLayout,
    lo: torch.Tensor,
    group: torch.Tensor,
    conics: _Conics,
) -> _Windows:
    """Sort the drawn windows into buckets of one (width, height) and place them in the image.

    Each box widens (right and down, into the z-buffer's padding at the image border) to its
    bucket's size: the extra pixels fail the exact test. Surfels that may reach the near plane
    get buckets of their own, which add a depth test. Sparse buckets join larger ones (see
    :func:`_merge_sparse_buckets`); a window's top-left pixel and polynomials depend on its
    surfel alone, and a larger window evaluates the same pixels the same way
    (:func:`_rasterise_surfels`), so a surfel is drawn bit for bit alike whatever else is
    drawn with it. Only the drawn windows (group below ``len(layout.shapes)``: visible, and
    their box holds a pixel to render; the full render draws no pixel outside a surfel's box,
    which bounds its disk with a margin against rounding) are placed and given polynomials.

    Args:
        surfels: the frustum-culled surfels (M).
        layout: the image's window buckets.
        lo: (2, M) int32 top-left pixel ``(u, v)`` of each box.
        group: (M,) int32 bucket of each window (see :func:`_surfel_groups`).
        conics: the conics of the M surfels.
    """
    height, width = layout.height, layout.width
    dropped = len(layout.shapes)
    counts = torch.bincount(group, minlength=dropped + 1).tolist()
    target = [*_merge_sparse_buckets(counts[:-1], layout.shapes), dropped]
    # int16 groups: the stable sort below is twice as fast as on int32.
    group = torch.tensor(target, dtype=torch.int16, device=lo.device).index_select(0, group)
    buckets, start = [], 0
    for g, count in enumerate(torch.bincount(group, minlength=dropped + 1)[:-1].tolist()):
        if count:
            buckets.append((*layout.shapes[g], g % 2 == 1, start, count))
            start += count
    # The windows, bucket by bucket: a stable sort of all, or of the drawn ones when few are.
    if 2 * start > group.shape[0]:
        order = torch.argsort(group, stable=True)[:start]
    else:
        drawn = torch.nonzero(group != dropped).view(-1)
        order = drawn.index_select(0, torch.argsort(group.index_select(0, drawn), stable=True))
    corner = lo.index_select(1, order)
    size = layout.sizes.index_select(1, group.index_select(0, order).to(torch.int32))
    pad_u, pad_v = (
        ((corner + size).amax(1) - corner.new_tensor([width, height])).clamp_(min=0).tolist()
        if start
        else (0, 0)
    )
    stride = width + -(-pad_u // _PAD_STEP) * _PAD_STEP  # few distinct strides: basis cache
    inside, inverse_depth = _window_polynomials(conics.select(order), corner)
    keys = inside.new_empty(3, start, 2)  # (tie-breaker, inverse depth) words of int64 keys
    keys[:2, :, 1 - _HIGH_WORD] = 0.0
    keys[2, :, 1 - _HIGH_WORD] = _tie_breakers(surfels.ids.index_select(0, order))
    keys[:, :, _HIGH_WORD] = inverse_depth
    base = corner[1].to(torch.int64).mul_(stride).add_(corner[0])
    return _Windows(inside, keys.view(3, -1), base, buckets, stride, height + pad_v)


def _summed_area(pixels: torch.Tensor) -> torch.Tensor:
    """((H + 1) * (W + 1),) int32 flat summed-area table of an (H, W) bool image: entry
    ``(v, u)`` counts the true pixels above row ``v`` and left of column ``u``."""
    height, width = pixels.shape
    table = torch.zeros((height + 1, width + 1), dtype=torch.int32, device=pixels.device)
    torch.cumsum(pixels.to(torch.int32).cumsum(0, dtype=torch.int32), 1, out=table[1:, 1:])
    return table.view(-1)


def _box_sums(sums: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, width: int) -> torch.Tensor:
    """(M,) int32 counts of the true pixels in the boxes ``[lo, hi]`` ((2, M) int32 ``(u, v)``,
    inclusive, in the image as :func:`_surfel_boxes` clips them; empty boxes count <= 0), from
    a flat :func:`_summed_area` table of a ``width``-wide image: four lookups per box (int32
    indices: the table is image-sized)."""
    last = hi + 1
    top, bottom = lo[1] * (width + 1), last[1] * (width + 1)
    corners = torch.stack((bottom + last[0], top + lo[0], top + last[0], bottom + lo[0]))
    value = sums.index_select(0, corners.view(-1)).view(4, -1)
    return value[0] + value[1] - value[2] - value[3]


def _merge_sparse_buckets(counts: list[int], shapes: tuple[tuple[int, int], ...]) -> list[int]:
    """The bucket each bucket's windows go to: sparse ones join the smallest that holds them.

    Every bucket costs a few tensor operations whatever its size, so a bucket of ``c`` windows
    of ``A`` pixels moves to the smallest-area bucket (same near flag, both sides at least as
    large) when that adds at most :data:`_MERGE_PIXELS` candidate pixels, ``c (A' - A)``.
    Sparsest buckets go first; a bucket that received windows may move on later.

    Args:
        counts: windows per bucket (group index ``g``, near flag ``g % 2``).
        shapes: ``(size_u, size_v)`` of each bucket.

    Returns:
        The target group of every group.
    """
    alive = {g: c for g, c in enumerate(counts) if c}
    by_area = sorted((shapes[g][0] * shapes[g][1], g) for g in alive)
    target = list(range(len(counts)))
    for g in sorted(alive, key=counts.__getitem__):
        area, (size_u, size_v) = shapes[g][0] * shapes[g][1], shapes[g]
        for other_area, h in by_area[bisect.bisect_left(by_area, (area, -1)) :]:
            if alive[g] * (other_area - area) > _MERGE_PIXELS:
                break
            other_u, other_v = shapes[h]
            if h != g and h in alive and h % 2 == g % 2 and other_u >= size_u and other_v >= size_v:
                alive[h] += alive.pop(g)
                target[g] = h
                break
    for g in range(len(target)):  # follow chains of moves
        while target[target[g]] != target[g]:
            target[g] = target[target[g]]
    return target


def _window_polynomials(conics: _Conics, corner: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``1 - q`` and the inverse depth in offsets ``(i, j)`` from each window's corner.

    Substituting ``du = i + a``, ``dv = j + b`` (``(a, b) = corner - centre``) into
    ``q = du (A du + B dv + D) + dv (C dv + E)`` and ``g0 + gu du + gv dv``.

    Args:
        conics: the surfels' conics.
        corner: (2, M) int32 top-left pixel ``(u0, v0)`` of each window.

    Returns:
        ``(inside, inverse_depth)``: (6, M) coefficients of ``1 - q`` on the monomials
        ``(i^2, i j, j^2, i, j, 1)`` and (3, M) of the inverse depth on ``(i, j, 1)``.
    """
    (A, C), B, (D, E), (gu, gv) = conics.AC, conics.B, conics.DE, conics.g_uv
    a, b = corner - conics.centre
    qa = torch.addcmul(D, A, a).addcmul_(B, b)  # dq/ddu at (a, b) minus A a
    qb = torch.addcmul(E, C, b)
    q_i = qa + A * a
    q_j = qb.addcmul(B, a).addcmul_(C, b)
    q_1 = (qa * a).addcmul_(qb, b)
    inside = torch.stack((A, B, C, q_i, q_j, q_1 - 1.0)).neg_()
    inverse_depth = torch.stack((gu, gv, torch.addcmul(conics.g0, gu, a).addcmul_(gv, b)))
    return inside, inverse_depth


def _tie_breakers(ids: torch.Tensor) -> torch.Tensor:
    """(K,) float32 z-buffer tie-breakers of (K,) int64 map indices (below :data:`_MAX_SURFELS`).

    Their bits are ``_TIE_TOP - ids``: positive normal floats, so a matrix product with one
    non-zero (unit) term reproduces them bit for bit, decreasing with the map index, so the
    max-reduced key of equal inverse depths holds the lowest.
    """
    return (_TIE_TOP - ids).to(torch.int32).view(torch.float32)


def _make_window_basis(
    size_u: int, size_v: int, stride: int, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """Monomials and flat pixel offsets of the row-major pixels ``(i, j)`` of a window.

    Returns:
        ``(basis, offsets)``: (A, 6) float32 monomials ``(i^2, i j, j^2, i, j, 1)`` with
        ``A = size_u * size_v`` (a matrix product with (6, m) coefficients evaluates m
        polynomials at every pixel) and (A, 1) int64 offsets ``j stride + i`` in a z-buffer
        with rows of ``stride`` pixels.
    """
    j, i = torch.meshgrid(
        torch.arange(size_v, device=device, dtype=torch.float32),
        torch.arange(size_u, device=device, dtype=torch.float32),
        indexing="ij",
    )
    i, j = i.reshape(-1), j.reshape(-1)
    basis = torch.stack((i * i, i * j, j * j, i, j, torch.ones_like(i)), dim=1)
    offsets = j.to(torch.int64).mul_(stride).add_(i.to(torch.int64))
    return basis, offsets[:, None]


_cached_window_basis = functools.lru_cache(maxsize=256)(_make_window_basis)


def _window_basis(
    size_u: int, size_v: int, stride: int, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_make_window_basis`, memoised for small windows (read-only constants)."""
    if size_u * size_v <= _BASIS_CACHE_AREA:
        return _cached_window_basis(size_u, size_v, stride, device)
    return _make_window_basis(size_u, size_v, stride, device)


def _chunk_shape(area: int) -> tuple[int, int]:
    """``(columns, rows)``: windows of ``area`` pixels per matrix product of
    :func:`_rasterise_surfels` (at least :data:`_GEMM_COLUMNS`) and pixels of each per product
    (all but for windows wider than ``_CHUNK / _GEMM_COLUMNS``)."""
    columns = max(_GEMM_COLUMNS, _CHUNK // area)
    return columns, min(area, _CHUNK // columns)


def _rasterise_surfels(windows: _Windows, keys: torch.Tensor) -> None:
    """Ray-disk test of all candidate pixels, z-buffered into ``keys`` in place.

    A candidate's key is the int64 read from two adjacent float32: the low word is the
    window's tie-breaker and the high word the inverse depth, with the sign of ``1 - q``
    (negative: the ray misses the disk). Positive floats order like their bits, so a
    max-reduction keeps per pixel the largest inverse depth, i.e. the nearest hit, and of equal
    ones the lowest surfel; misses are negative keys and never win. A matrix product per chunk
    of windows writes the keys in place (the tie-breaker is a constant polynomial), a second
    one ``1 - q``, and one ``copysign`` applies the test. Every product has at least
    :data:`_GEMM_COLUMNS` columns (a chunk of fewer windows repeats some, which writes the same
    keys again; wide windows go by blocks of pixel rows), so that every window takes the same
    matrix product kernel, whatever other windows share its chunk.

    Args:
        windows: the candidate windows of one camera.
        keys: (windows.buffer_rows * windows.stride,) int64 flat z-buffer, in place
            (:data:`_NO_KEY` where empty).
    """
    pairs = windows.keys.view(3, -1, 2)
    for size_u, size_v, near, first, count in windows.buckets:
        area = size_u * size_v
        basis, offsets = _window_basis(size_u, size_v, windows.stride, keys.device)
        columns, rows = _chunk_shape(area)
        blocks = [
            (basis[row : row + rows], offsets[row : row + rows]) for row in range(0, area, rows)
        ]
        for start in range(first, first + count, columns):
            stop = min(start + columns, first + count)
            chunk = (
                slice(start, stop)
                if stop - start >= _GEMM_COLUMNS
                else torch.arange(_GEMM_COLUMNS).remainder_(stop - start).add_(start)
            )
            keys_pairs = pairs[:, chunk].reshape(3, -1)
            polynomials, base = windows.inside[:, chunk], windows.base[chunk]
            for block, block_offsets in blocks:
                candidates = torch.mm(block[:, 3:], keys_pairs)  # (rows, 2 m)
                inside = torch.mm(block, polynomials)  # (rows, m)
                inverse_depth = candidates[:, _HIGH_WORD::2]
                if near:  # hits must also be in front of the near plane
                    miss = (inside < 0) | (inverse_depth <= 0) | (inverse_depth >= 1.0 / MIN_DEPTH)
                    inverse_depth.masked_fill_(miss, -1.0)
                else:
                    inverse_depth.copysign_(inside)
                slots = torch.add(base, block_offsets)
                keys.scatter_reduce_(
                    0, slots.view(-1), candidates.view(torch.int64).view(-1), "amax"
                )


def _resolve_surfel_keys(
    keys: torch.Tensor,
    surfels: _SurfelCandidates,
    size: int,
    ids: torch.Tensor,
    depth: torch.Tensor,
    normals: torch.Tensor,
) -> None:
    """Write the surfel ids, depths and normals of a z-buffer into the output images.

    Args:
        keys: (P,) int64 z-buffer (see :func:`_rasterise_surfels`).
        surfels: the camera's candidate surfels.
        size: number of surfels N in the map.
        ids: (P,) int64 output, map index or -1.
        depth: (P,) float32 output, z-depth or 0.
        normals: (3, P) float32 output, unit camera-frame normal or 0.
    """
    count = surfels.ids.shape[0]
    low, high = _key_words(keys)
    inverse_depth = high.view(torch.float32)
    hit = inverse_depth > 0  # empty pixels: _NO_KEY or a miss, high word -0.0 or negative
    torch.reciprocal(torch.where(hit, inverse_depth, math.inf), out=depth)  # empty: 0
    found = torch.sub(_TIE_TOP, torch.where(hit, low, _TIE_TOP - size))  # `size`: none
    ids.copy_(found).masked_fill_(~hit, -1)
    position = torch.empty(size + 1, dtype=torch.int32, device=keys.device)  # map -> candidate
    position[size] = count
    position.index_copy_(0, surfels.ids, torch.arange(count, dtype=torch.int32, device=keys.device))
    local = position.index_select(0, found)
    table = torch.cat((surfels.normals, surfels.normals.new_zeros(3, 1)), dim=1)  # (3, M + 1)
    for row, out in zip(table, normals, strict=True):
        torch.index_select(row, 0, local, out=out)


def _check_surfels(centers: torch.Tensor, normals: torch.Tensor, radii: torch.Tensor) -> None:
    check_shape(centers, "N,3", "centers")
    check_shape(normals, "N,3", "normals")
    check_shape(radii, "N", "radii")
    n = centers.shape[0]
    if normals.shape[0] != n or radii.shape[0] != n:
        raise ShapeError(
            f"centers, normals and radii must have the same length N, got "
            f"{n}, {normals.shape[0]} and {radii.shape[0]}"
        )
    _check_map_size(n, "surfels", _MAX_SURFELS)
    if n == 0:
        return
    # One reduction each decides the common case; the exact (slower) tests run only when it
    # is inconclusive: a NaN entry or a real violation.
    if not bool(radii.min() > 0) and bool((radii <= 0).any()):
        raise ValueError("surfel radii must be positive")
    if normals.dtype in (torch.float32, torch.float64):
        # A zero row has a zero projection on any direction; a non-zero one almost never does.
        direction = torch.tensor(_PROBE_DIRECTION, dtype=normals.dtype, device=normals.device)
        if bool(torch.mv(normals, direction).abs_().min() > 0):
            return
    if bool((normals == 0).all(-1).any()):
        raise ValueError("surfel normals must be non-zero")


class SurfelIndexRenderer:
    """Renders the global surfel index map (seed 1 Sec. III-A) of one surfel map, view by view.

    For many renders of the same map: the map is validated and converted once and, with
    ``cell_size_m``, its surfels are grouped into cubic cells whose bounding spheres are culled
    against each view's frustum first, so only the surfels of the cells that the frustum cuts
    are tested one by one. Renders are bit for bit those of :func:`render_surfel_index` (the
    cells change the work, not the candidate set). The map tensors must not change afterwards.

    Args:
        centers: (N, 3) surfel centres, world frame (metres).
        normals: (N, 3) surfel normals, world frame (any non-zero length).
        radii: (N,) disk radii in metres (> 0).
        cell_size_m: edge of the culling cells in metres, or ``None`` to test every surfel.

    Raises:
        ShapeError: wrong shapes.
        ValueError: radii ``<= 0``, zero normals, a non-positive cell size.

    Example:
        >>> renderer = SurfelIndexRenderer(
        ...     torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[0.0, 0.0, -1.0]]),
        ...     torch.tensor([0.1]))
        >>> out = renderer.render(torch.eye(4)[None], PinholeCamera.from_fov(64, 48, 1.0))
        >>> int(out.ids[0, 24, 32]), float(out.depth[0, 24, 32])
        (0, 2.0)
    """

    def __init__(
        self,
        centers: torch.Tensor,
        normals: torch.Tensor,
        radii: torch.Tensor,
        *,
        cell_size_m: float | None = 0.25,
    ) -> None:
        _check_surfels(centers, normals, radii)
        if cell_size_m is not None and not (math.isfinite(cell_size_m) and cell_size_m > 0):
            raise ValueError(f"cell_size_m must be positive, got {cell_size_m!r}")
        self.centers = centers.to(torch.float32)
        self.normals = normals.to(torch.float32)
        self.radii = radii.to(torch.float32)
        self.cells = (
            None
            if cell_size_m is None
            else _SurfelCells.build(self.centers, self.normals, self.radii, cell_size_m)
        )

    def __len__(self) -> int:
        return self.centers.shape[0]

    @functools.cached_property
    def _extents(self) -> torch.Tensor:
        """(N, 3) half-extents of the disks' boxes (:func:`_disk_extents`), for masked renders
        without cells (made at the first)."""
        return _disk_extents(self.normals, self.radii)

    def _candidates(
        self, view: _View, height: int, width: int, pixel_sums: torch.Tensor | None
    ) -> _SurfelCandidates:
        """The surfels that may be visible in ``view``, in the camera frame.

        With ``pixel_sums`` (see :func:`_summed_area`), only those that may be seen at a pixel
        to render: the cells, then the surfels, whose axis-aligned boxes (world-frame boxes
        rotated into the camera frame) reach one (:func:`_box_touches`). Every transform is
        elementwise (:func:`_rigid_columns`), so a surfel is drawn alike in any subset.
        """
        if self.cells is None:
            positions = _frustum_candidates(self.centers, self.radii, view, height, width)
            ids, data = positions, (self.centers, self.normals, self.radii)
        else:
            positions = self.cells.cull(view, height, width, pixel_sums)
            ids = self.cells.ids.index_select(0, positions)
            data = (self.cells.centers, self.cells.normals, self.cells.radii)
        centers, normals, radii = data
        c = view.to_camera(centers.index_select(0, positions).T, elementwise=True)
        if pixel_sums is not None:
            extents = self._extents if self.cells is None else self.cells.extents
            e = view.R_cw.abs() @ extents.index_select(0, positions).T
            touches = [ids.new_zeros(0, dtype=torch.bool)]  # (no surfels at all)
            for start in range(0, ids.shape[0], _SURFEL_CHUNK):
                chunk = slice(start, start + _SURFEL_CHUNK)
                touches.append(_box_touches(c[:, chunk], e[:, chunk], view, pixel_sums))
            keep = torch.cat(touches).nonzero().view(-1)
            positions, ids, c = positions[keep], ids[keep], c.index_select(1, keep)
        n = _rigid_columns(view.R_cw, normals.index_select(0, positions).T)
        n = n / (n * n).sum(0).sqrt_()
        return _SurfelCandidates(ids, c, n, radii.index_select(0, positions))

    @torch.no_grad()
    def render(
        self,
        T_wc: torch.Tensor,
        camera: PinholeCamera,
        *,
        cull_backfaces: bool = False,
        pixels: torch.Tensor | None = None,
    ) -> SurfelRender:
        """Render the map from a batch of poses; see :func:`render_surfel_index`.

        Args:
            T_wc: (B, 4, 4) camera-to-world poses.
            camera: one ideal pinhole camera or a batch of ``B`` (same image size).
            cull_backfaces: also drop surfels whose normal points away from the camera.
            pixels: (B, H, W) bool, the pixels to render, or ``None`` for all.

        Returns:
            A :class:`SurfelRender` with ids (B, H, W), depth (B, H, W), normals (B, 3, H, W).
        """
        batch = _check_poses(T_wc)
        camera = _check_camera(camera, batch)
        if camera.distortion is not None:
            raise ValueError(
                "render_surfel_index needs an ideal pinhole camera (distortion=None); undistort "
                "the images and keypoints first (PinholeCamera.undistort_points)"
            )
        height, width = camera.height, camera.width
        if pixels is not None:
            check_shape(pixels, f"{batch},{height},{width}", "pixels")
            if pixels.dtype != torch.bool:
                raise ValueError(f"pixels must be a bool mask, got {pixels.dtype}")
        device = self.centers.device
        ids = torch.empty((batch, height * width), dtype=torch.int64, device=device)
        depth = torch.empty((batch, height * width), dtype=torch.float32, device=device)
        normals_cam = torch.empty((batch, 3, height * width), dtype=torch.float32, device=device)
        for b, view in enumerate(_views(T_wc, camera)):
            sums = None if pixels is None else _summed_area(pixels[b])
            surfels = self._candidates(view, height, width, sums)
            windows = _surfel_windows(surfels, view, height, width, cull_backfaces, sums)
            rows, stride = windows.buffer_rows, windows.stride
            keys = torch.full((rows * stride,), _NO_KEY, dtype=torch.int64, device=device)
            _rasterise_surfels(windows, keys)
            if pixels is None:
                if (rows, stride) != (height, width):  # drop the padding
                    keys = keys.view(rows, stride)[:height, :width].reshape(-1)
                _resolve_surfel_keys(keys, surfels, len(self), ids[b], depth[b], normals_cam[b])
                continue
            # The other pixels saw only some of their surfels: -1, 0, 0 there.
            index = torch.nonzero(pixels[b].reshape(-1)).view(-1)
            found_ids, found_depth = ids.new_empty(len(index)), depth.new_empty(len(index))
            found_normals = normals_cam.new_empty(3, len(index))
            keys = keys.index_select(0, index + index // width * (stride - width))
            _resolve_surfel_keys(keys, surfels, len(self), found_ids, found_depth, found_normals)
            ids[b].fill_(-1).index_copy_(0, index, found_ids)
            depth[b].zero_().index_copy_(0, index, found_depth)
            normals_cam[b].zero_().index_copy_(1, index, found_normals)
        return SurfelRender(
            ids.view(batch, height, width),
            depth.view(batch, height, width),
            normals_cam.view(batch, 3, height, width),
        )


def render_surfel_index(
    centers: torch.Tensor,
    normals: torch.Tensor,
    radii: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    *,
    cull_backfaces: bool = False,
    pixels: torch.Tensor | None = None,
) -> SurfelRender:
    """Render the global surfel index map (seed 1 Sec. III-A) of oriented disks.

    A pixel shows the nearest surfel whose disk the ray through the pixel centre hits; its
    depth is the exact z-depth of that hit. Disks are two-sided unless ``cull_backfaces``.

    With ``pixels``, only the surfels whose candidate window holds one of those pixels are
    drawn (each surfel's window is the one it has in the full render, so every surfel that
    covers such a pixel is drawn): ids, depths and normals at those pixels are bit for bit
    those of the full render, and -1, 0, 0 at the other pixels. Use it when only a few
    regions are read (e.g. the keypoint disks of :func:`neighbour_surfels`).

    Args:
        centers: (N, 3) surfel centres, world frame (metres).
        normals: (N, 3) surfel normals, world frame (any non-zero length; normalised here).
        radii: (N,) disk radii in metres (> 0).
        T_wc: (B, 4, 4) camera-to-world poses.
        camera: one ideal pinhole camera or a batch of ``B`` (same image size).
        cull_backfaces: also drop surfels whose normal points away from the camera.
        pixels: (B, H, W) bool, the pixels to render, or ``None`` for all.

    Returns:
        A :class:`SurfelRender` with ids (B, H, W), depth (B, H, W), normals (B, 3, H, W).

    Raises:
        ShapeError: wrong shapes, ``B = 0`` or a camera batch that does not match ``T_wc``,
            ``pixels`` not (B, H, W).
        ValueError: non-finite poses, radii ``<= 0``, zero normals, a distorted camera, a
            ``pixels`` mask that is not bool.

    Example:
        >>> cam = PinholeCamera.from_fov(64, 48, 1.0)
        >>> out = render_surfel_index(
        ...     torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[0.0, 0.0, -1.0]]),
        ...     torch.tensor([0.1]), torch.eye(4)[None], cam)
        >>> int(out.ids[0, 24, 32]), float(out.depth[0, 24, 32])
        (0, 2.0)
    """
    _check_poses(T_wc)
    renderer = SurfelIndexRenderer(centers, normals, radii, cell_size_m=None)
    return renderer.render(T_wc, camera, cull_backfaces=cull_backfaces, pixels=pixels)


# ---------------------------------------------------------------------------- points


def _window_min(x: torch.Tensor, size: int, dim: int) -> torch.Tensor:
    """Sliding-window minimum ``y[j] = min(x[j : j + size])`` along ``dim``.

    Uses doubling (windows of 1, 2, 4, ... then two overlapping windows), so it costs
    ``O(log size)`` elementwise minima. The output is ``size - 1`` shorter than ``x``.
    """
    span, y = 1, x
    while 2 * span <= size:
        length = y.shape[dim] - span
        y = torch.minimum(y.narrow(dim, 0, length), y.narrow(dim, span, length))
        span *= 2
    length = x.shape[dim] - size + 1
    if span == size:
        return y.narrow(dim, 0, length)
    return torch.minimum(y.narrow(dim, 0, length), y.narrow(dim, size - span, length))


def _window_min_2d(x: torch.Tensor, size: int) -> torch.Tensor:
    """``size x size`` sliding-window minimum over the last two dimensions (shrinks both)."""
    return _window_min(_window_min(x, size, -2), size, -1)


@dataclass(frozen=True)
class _AnchorLayout:
    """Padded anchor images, one per pass, for splats of sizes up to ``max_size``.

    An anchor is the top-left pixel of a splat, stored at ``(v + offset, u + offset)`` with
    ``offset = max_size``, clamped into the padded image. A splat of size ``k`` covers pixel
    ``u`` when its anchor lies in ``[u - k + 1, u]`` (a trailing window of ``k``), so only
    padded columns ``1 .. offset + W - 1`` are ever read: column 0 and the last column collect
    the anchors of splats that miss the image. The same holds for rows.
    """

    sizes: tuple[int, ...]
    height: int
    width: int

    @property
    def offset(self) -> int:
        return self.sizes[-1]

    @property
    def shape(self) -> tuple[int, int, int]:
        border = self.offset + 1
        return len(self.sizes), self.height + border, self.width + border

    def merge(self, anchors: torch.Tensor) -> torch.Tensor:
        """(H, W) nearest keys over all passes of (L, Hp, Wp) anchor images.

        ``min_k window_k(A_k)`` is evaluated Horner-style from the largest size down, since a
        window of ``k`` is a window of ``k - j`` after one of ``j + 1``:
        ``acc = min(window_{k_{i+1} - k_i + 1}(acc), A_{k_i})``, then a final window of
        ``k_0``. Each forward window of ``s`` moves the image origin by ``s - 1``.
        """
        acc, origin = anchors[-1], 0
        for level in range(len(self.sizes) - 2, -1, -1):
            step = self.sizes[level + 1] - self.sizes[level]
            acc, origin = _window_min_2d(acc, step + 1), origin + step
            acc = torch.minimum(acc, anchors[level, origin:, origin:])
        acc = _window_min_2d(acc, self.sizes[0])
        first = self.offset - (origin + self.sizes[0] - 1)  # = 1
        return acc[first : first + self.height, first : first + self.width]


def _scatter_point_anchors(
    points_world: torch.Tensor,
    first_id: int,
    view: _View,
    sizes: PointSizes,
    layout: _AnchorLayout,
    anchors: torch.Tensor,
) -> None:
    """Scatter the keys of a chunk of points to the anchors of their splats (in place).

    Args:
        points_world: (n, 3) world points.
        first_id: map index of the chunk's first point.
        view: the camera.
        sizes: splat sizes.
        layout: anchor image layout.
        anchors: (L, Hp, Wp) int64 anchor images.
    """
    points_cam = view.to_camera(points_world.T)
    total = points_cam.sum(0)
    valid = (total - total) == 0  # false for NaN / inf coordinates
    x, y, z = points_cam
    valid &= z > MIN_DEPTH
    inv_z = z.reciprocal()
    xn, yn = x.mul_(inv_z), y.mul_(inv_z)
    if view.camera.distortion is not None:
        xn, yn = view.camera.distort(torch.stack((xn, yn), dim=-1)).unbind(-1)
        valid &= torch.isfinite(xn) & torch.isfinite(yn)  # the polynomial can overflow
    num_levels, rows, cols = anchors.shape
    shift = layout.offset
    if num_levels == 1:
        half, level = 0.5 * layout.sizes[0], None
    else:
        level = sizes.level_index(z)
        half = torch.tensor(layout.sizes, dtype=torch.float32, device=z.device)[level] * 0.5
    u_lo = (xn * view.fx + (view.cx + shift)).sub_(half).ceil_().clamp_(0, cols - 1)
    v_lo = (yn * view.fy + (view.cy + shift)).sub_(half).ceil_().clamp_(0, rows - 1)
    slots = v_lo.to(torch.int64).mul_(cols).add_(u_lo.to(torch.int64))
    if level is not None:
        slots.add_(level * (rows * cols))
    slots.masked_fill_(~valid, 0)  # (0, 0) of pass 0 is never read
    ids = torch.arange(first_id, first_id + z.shape[0], device=z.device)
    anchors.view(-1).scatter_reduce_(0, slots, _pack_keys(z, ids), "amin")


def _check_points(points: torch.Tensor, colors: torch.Tensor) -> None:
    check_shape(points, "N,3", "points")
    check_shape(colors, "N,3", "colors")
    if colors.shape[0] != points.shape[0]:
        raise ShapeError(
            f"colors must have one row per point: {colors.shape[0]} != {points.shape[0]}"
        )
    _check_map_size(points.shape[0], "points")


@torch.no_grad()
def render_points(
    points: torch.Tensor,
    colors: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    sizes: PointSizes | None = None,
) -> PointRender:
    """Render a coloured point cloud as square splats with a z-buffer (seed 2 Sec. III-D1).

    The splat size of each point follows ``sizes`` (default: 1 pixel): fixed, per-point inverse
    depth (Eq. 2) or the multi-pass scheme; see :class:`PointSizes`. Splats are flat: every
    pixel of a splat gets the point's depth; the nearest splat wins (ties: lower index).

    Args:
        points: (N, 3) points, world frame (metres); rows with NaN/inf are culled.
        colors: (N, 3) colours in [0, 1].
        T_wc: (B, 4, 4) camera-to-world poses.
        camera: one camera or a batch of ``B`` (same image size); distortion allowed.
        sizes: splat sizes.

    Returns:
        A :class:`PointRender`: rgb (B, 3, H, W), depth (B, 1, H, W), ids (B, H, W),
        mask (B, 1, H, W).

    Raises:
        ShapeError: wrong shapes, ``B = 0`` or a camera batch that does not match ``T_wc``.
        ValueError: non-finite poses.

    Example:
        >>> cam = PinholeCamera.from_fov(64, 48, 1.0)
        >>> out = render_points(torch.tensor([[0.0, 0.0, 2.0]]), torch.ones(1, 3),
        ...                     torch.eye(4)[None], cam, PointSizes.fixed(3))
        >>> int(out.mask.sum()), float(out.depth.max())
        (9, 2.0)
    """
    batch = _check_poses(T_wc)
    _check_points(points, colors)
    camera = _check_camera(camera, batch)
    sizes = PointSizes() if sizes is None else sizes
    layout = _AnchorLayout(sizes.pass_sizes(), camera.height, camera.width)
    points = points.to(torch.float32)
    keys = []
    for view in _views(T_wc, camera):
        anchors = _empty_keys(layout.shape, points.device)
        for first in range(0, points.shape[0], _CHUNK):
            chunk = points[first : first + _CHUNK]
            _scatter_point_anchors(chunk, first, view, sizes, layout, anchors)
        keys.append(layout.merge(anchors))
    ids, depth = _unpack_keys(torch.stack(keys))
    mask = ids >= 0
    rgb = _gather_channels_first(colors.to(torch.float32), ids).masked_fill_(~mask[:, None], 0.0)
    return PointRender(rgb, depth[:, None], ids, mask[:, None])


def see_through_fraction(
    depth: torch.Tensor, occluder_depth: float, region: torch.Tensor | None = None
) -> torch.Tensor:
    """Fraction of pixels where a render sees past an occluder (seed 2 Fig. 4).

    A pixel "sees through" when it has no depth (0) or a depth beyond ``occluder_depth``.

    Args:
        depth: (B, 1, H, W) or (B, H, W) rendered z-depth, 0 where empty.
        occluder_depth: largest depth (metres) of the occluding surface.
        region: optional (H, W) or (B, H, W) bool mask of the pixels where the occluder is
            expected (default: all pixels).

    Returns:
        (B,) float32 fractions in [0, 1].

    Example:
        >>> see_through_fraction(torch.tensor([[[1.0, 0.0], [5.0, 1.0]]]), 2.0)
        tensor([0.5000])
    """
    if depth.dim() == 4:
        check_shape(depth, "B,1,H,W", "depth")
        depth = depth[:, 0]
    check_shape(depth, "B,H,W", "depth")
    through = (depth == 0) | (depth > occluder_depth)
    if region is None:
        region = torch.ones_like(through)
    region = region.expand_as(through)
    counts = region.flatten(1).sum(-1).clamp_min(1)
    return (through & region).flatten(1).sum(-1).float() / counts


# ---------------------------------------------------------------------------- neighbours


def neighbour_surfels(
    ids: torch.Tensor, keypoints: torch.Tensor, radius_px: torch.Tensor | float
) -> torch.Tensor:
    """Distinct surfel ids within each keypoint's radius (seed 1's neighbouring surfel set).

    A pixel belongs to a keypoint when its centre is within ``radius_px`` (Euclidean) of the
    keypoint; -1 entries of the id map are ignored. For OpenCV keypoints whose ``size`` is a
    diameter, pass ``size / 2``.

    Args:
        ids: (H, W) or (B, H, W) int64 surfel index map (-1 where none).
        keypoints: (K, 2) or (B, K, 2) pixel coordinates ``(u, v)``, batched like ``ids``.
        radius_px: scalar, (K,) or (B, K) radii in pixels (>= 0).

    Returns:
        (K, M) or (B, K, M) int64: each row the sorted distinct ids, padded with -1; ``M`` is
        the largest set size (0 when all sets are empty).

    Raises:
        ShapeError: shapes that do not match.
        ValueError: non-finite keypoints or negative / non-finite radii.

    Example:
        >>> ids = torch.tensor([[0, 1, -1], [2, 2, 3]])
        >>> neighbour_surfels(ids, torch.tensor([[0.0, 0.0]]), 1.0)
        tensor([[0, 1, 2]])
    """
    unbatched = ids.dim() == 2
    if unbatched:
        ids, keypoints = ids[None], keypoints[None]
    check_shape(ids, "B,H,W", "ids")
    check_shape(keypoints, "B,K,2", "keypoints")
    if keypoints.shape[0] != ids.shape[0]:
        raise ShapeError(
            f"keypoints batch {keypoints.shape[0]} does not match ids batch {ids.shape[0]}"
        )
    check_finite(keypoints, "keypoints")
    batch, height, width = ids.shape
    count = keypoints.shape[1]
    radius = torch.as_tensor(radius_px, dtype=torch.float32, device=keypoints.device)
    try:
        radius = radius.expand(batch, count) if radius.dim() < 2 else radius
    except RuntimeError as exc:
        raise ShapeError(f"radius_px of shape {tuple(radius.shape)} does not match K") from exc
    if radius.shape != (batch, count):
        raise ShapeError(f"radius_px must be scalar, (K,) or (B, K), got {tuple(radius.shape)}")
    if not bool((torch.isfinite(radius) & (radius >= 0)).all()):
        raise ValueError("radius_px must be finite and non-negative")
    result = _neighbours_flat(ids, keypoints.to(torch.float32), radius)
    result = result.view(batch, count, result.shape[-1])
    return result[0] if unbatched else result


def _inside(pu: torch.Tensor, u: torch.Tensor, dv2: torch.Tensor, r2: torch.Tensor) -> torch.Tensor:
    """Whether float pixel columns ``pu`` lie in the disks, given each row's squared offset
    ``dv2`` and squared radius ``r2`` (all broadcast alike); the one float32 membership test."""
    return (pu - u).square() + dv2 <= r2


def _disk_rows(
    keypoints: torch.Tensor, radius: torch.Tensor, height: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Image rows each keypoint's disk may cover.

    Args:
        keypoints: (N, 2) float32 pixel coordinates ``(u, v)``.
        radius: (N,) float32 radii.
        height: image height.

    Returns:
        owner: (R,) int64 keypoint of every row, ascending.
        rows: (R,) int64 row index in ``[0, height)``: the rows within ``floor(radius) + 1`` of
        the keypoint's nearest pixel row, which hold every pixel of the disk.
    """
    reach = torch.floor(radius) + 1
    centre = torch.floor(keypoints[:, 1] + 0.5)
    first = (centre - reach).clamp(0, height).long()
    last = (centre + reach).clamp(-1, height - 1).long()
    count = (last - first + 1).clamp_min(0)
    owner = torch.repeat_interleave(torch.arange(len(count), device=count.device), count)
    rank = torch.arange(len(owner), device=owner.device) - (count.cumsum(0) - count)[owner]
    return owner, first[owner] + rank


def _segment_end(
    u: torch.Tensor, dv2: torch.Tensor, r2: torch.Tensor, width: int, side: int
) -> torch.Tensor:
    """(R,) int64 last pixel column of each row's disk segment towards ``side`` (-1 left, +1
    right), clamped to ``[-1, width]``.

    At image-scale coordinates the square-root estimate is within one pixel of the float32
    test of :func:`_inside`, which decides: the segment end is the outermost of the estimate's
    neighbours inside the disk (beyond the estimate on an empty row, so that the ends cross).
    """
    half = (r2 - dv2).clamp_min(0).sqrt()
    estimate = torch.ceil(u - half) if side < 0 else torch.floor(u + half)
    estimate = estimate.clamp(-1, width)
    outer, inner = estimate + side, estimate - side
    end = torch.where(_inside(estimate, u, dv2, r2), estimate, inner)
    end = torch.where(_inside(outer, u, dv2, r2), outer, end)
    return end.long().clamp(-1, width)


def _disk_segments(
    keypoints: torch.Tensor, radius: torch.Tensor, height: int, width: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pixels of the keypoint disks as non-empty row segments, clipped to the image.

    Args:
        keypoints: (N, 2) float32 pixel coordinates ``(u, v)``.
        radius: (N,) float32 radii.
        height: image height.
        width: image width.

    Returns:
        ``(owner, rows, left, right)``, each (S,) int64: the keypoint, image row and first and
        last column (inclusive) of every segment, keypoint by keypoint.
    """
    owner, rows = _disk_rows(keypoints, radius, height)
    u, r2 = keypoints[owner, 0], radius[owner].square()
    dv2 = (rows - keypoints[owner, 1]).square()
    left = _segment_end(u, dv2, r2, width, -1).clamp_min(0)
    right = _segment_end(u, dv2, r2, width, 1).clamp_max(width - 1)
    keep = left <= right
    return owner[keep], rows[keep], left[keep], right[keep]


def keypoint_disk_mask(
    keypoints: torch.Tensor, radius_px: torch.Tensor | float, height: int, width: int
) -> torch.Tensor:
    """The pixels :func:`neighbour_surfels` reads: those within each keypoint's radius.

    Pass it as ``pixels`` to :meth:`SurfelIndexRenderer.render` when only the neighbour sets
    are needed.

    Args:
        keypoints: (K, 2) finite pixel coordinates ``(u, v)``.
        radius_px: scalar or (K,) radii in pixels (finite, >= 0).
        height: image height H.
        width: image width W.

    Returns:
        (H, W) bool, true at the pixel centres within ``radius_px`` of a keypoint.

    Raises:
        ShapeError: keypoints not (K, 2), radii neither scalar nor (K,).
        ValueError: non-finite keypoints, negative or non-finite radii.

    Example:
        >>> keypoint_disk_mask(torch.tensor([[1.0, 1.0]]), 1.0, 3, 4).int()
        tensor([[0, 1, 0, 0],
                [1, 1, 1, 0],
                [0, 1, 0, 0]], dtype=torch.int32)
    """
    return KeypointDisks.of(keypoints, radius_px, height, width).mask()


@dataclass(frozen=True)
class KeypointDisks:
    """The pixels within each keypoint's radius in one image, as row segments.

    Made once per image, they give both the pixels :func:`neighbour_surfels` reads
    (:meth:`mask`, as :func:`keypoint_disk_mask`) and, from the rendered index map, the
    neighbouring surfel sets (:meth:`neighbours`, as :func:`neighbour_surfels`).

    Attributes:
        owner: (S,) int64 keypoint of every segment, keypoint by keypoint.
        rows: (S,) int64 image row of every segment.
        left: (S,) int64 first column (inclusive) of every segment.
        right: (S,) int64 last column (inclusive) of every segment.
        count: number of keypoints K.
        height: image height H.
        width: image width W.

    Example:
        >>> disks = KeypointDisks.of(torch.tensor([[0.0, 0.0]]), 1.0, 2, 3)
        >>> disks.neighbours(torch.tensor([[0, 1, -1], [2, 2, 3]]))
        tensor([[0, 1, 2]])
    """

    owner: torch.Tensor
    rows: torch.Tensor
    left: torch.Tensor
    right: torch.Tensor
    count: int
    height: int
    width: int

    @classmethod
    def of(
        cls, keypoints: torch.Tensor, radius_px: torch.Tensor | float, height: int, width: int
    ) -> KeypointDisks:
        """The disks of (K, 2) ``keypoints`` with scalar or (K,) ``radius_px`` in an image.

        Raises:
            ShapeError: keypoints not (K, 2), radii neither scalar nor (K,).
            ValueError: non-finite keypoints, negative or non-finite radii.
        """
        check_shape(keypoints, "K,2", "keypoints")
        check_finite(keypoints, "keypoints")
        keypoints = keypoints.to(torch.float32)
        radius = torch.as_tensor(radius_px, dtype=torch.float32, device=keypoints.device)
        if radius.dim() > 1 or radius.numel() not in (1, keypoints.shape[0]):
            raise ShapeError(f"radius_px must be scalar or (K,), got {tuple(radius.shape)}")
        if not bool((torch.isfinite(radius) & (radius >= 0)).all()):
            raise ValueError("radius_px must be finite and non-negative")
        radius = radius.expand(keypoints.shape[0])
        segments = _disk_segments(keypoints, radius, height, width)
        return cls(*segments, keypoints.shape[0], height, width)

    def mask(self) -> torch.Tensor:
        """(H, W) bool, true at the pixel centres within a keypoint's radius."""
        start = self.rows * self.width
        steps = torch.zeros(self.height * self.width + 1, dtype=torch.int32, device=start.device)
        steps.index_add_(0, start + self.left, torch.ones_like(self.left, dtype=torch.int32))
        ends = torch.full_like(self.right, -1, dtype=torch.int32)
        steps.index_add_(0, start + self.right + 1, ends)
        return steps.cumsum_(0)[:-1].view(self.height, self.width) > 0

    def neighbours(self, ids: torch.Tensor) -> torch.Tensor:
        """(K, M) sorted distinct surfel ids of (H, W) ``ids`` in each disk, padded with -1.

        Raises:
            ShapeError: ``ids`` not (H, W).
        """
        check_shape(ids, f"{self.height},{self.width}", "ids")
        return _segment_sets(ids[None], self.owner, self.rows, self.left, self.right, self.count)


def _run_starts(
    ids: torch.Tensor, first: torch.Tensor, last: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat pixels that start a run of equal ids within each row segment.

    A segment ``[first, last]`` (flat pixel indices within one image row) holds the same ids
    as its first pixel plus the pixels that differ from their left neighbour.

    Args:
        ids: (B, H, W) surfel index map.
        first, last: (S,) int64 flat pixel bounds of non-empty segments.

    Returns:
        count: (S,) int64 number of run starts of every segment.
        pixel: (E,) int64 flat pixel index of every run start, segment by segment.
    """
    change = torch.zeros_like(ids, dtype=torch.bool)
    change[..., 1:] = ids[..., 1:] != ids[..., :-1]
    change = change.reshape(-1)
    before = torch.zeros(change.numel() + 1, dtype=torch.int64, device=ids.device)
    torch.cumsum(change, 0, out=before[1:])  # before[f]: changes at flat pixels < f
    # The changes in (first, last] are positions[skip:skip + count - 1]; a zero sentinel
    # stands in for the segment's first pixel, written afterwards.
    positions = torch.cat([change.nonzero().squeeze(1), before[:1]])
    skip = before[first + 1]
    count = before[last + 1] - skip + 1
    start = count.cumsum(0) - count
    index = torch.arange(int(count.sum()), device=ids.device)
    index += torch.repeat_interleave(skip - 1 - start, count)
    pixel = positions[index.clamp_min_(0)]
    pixel[start] = first
    return count, pixel


def _padded_sets(owner: torch.Tensor, values: torch.Tensor, count: int) -> torch.Tensor:
    """(count, M) sorted distinct non-negative ``values`` of every owner, padded with -1.

    Args:
        owner: (E,) int64 owner of every value in ``[0, count)``.
        values: (E,) int64 values >= -1; -1 ones are ignored.
        count: number of owners.
    """
    base = int(values.max()) + 2 if len(values) else 1
    key = (owner * base + (values + 1)).sort(stable=True).values  # stable: radix sort on CPU
    first = torch.ones_like(key, dtype=torch.bool)
    first[1:] = key[1:] != key[:-1]
    key = key[first & (key % base != 0)]
    owner, values = key // base, key % base - 1
    sizes = torch.bincount(owner, minlength=count)
    width = int(sizes.max()) if count else 0
    rank = torch.arange(len(key), device=key.device) - (sizes.cumsum(0) - sizes)[owner]
    out = torch.full((count * width,), -1, dtype=torch.int64, device=key.device)
    return out.index_put_((owner * width + rank,), values).view(count, width)


def _neighbours_flat(
    ids: torch.Tensor, keypoints: torch.Tensor, radius: torch.Tensor
) -> torch.Tensor:
    """(B * K, M) neighbour sets; see :func:`neighbour_surfels`.

    Every keypoint scans only its own disk, as ragged row segments (no padding to the largest
    radius): the ids of a segment are those of its runs of equal ids, and one sort of
    ``(keypoint, id)`` keys makes the sets distinct.
    """
    batch, height, width = ids.shape
    kp, rad = keypoints.reshape(-1, 2), radius.reshape(-1)
    owner, rows, left, right = _disk_segments(kp, rad, height, width)
    camera = owner // max(keypoints.shape[1], 1)
    return _segment_sets(ids, owner, camera * height + rows, left, right, kp.shape[0])


def _segment_sets(
    ids: torch.Tensor,
    owner: torch.Tensor,
    rows: torch.Tensor,
    left: torch.Tensor,
    right: torch.Tensor,
    count: int,
) -> torch.Tensor:
    """(count, M) distinct ids of (B, H, W) ``ids`` in the (S,) row segments of each owner.

    ``rows`` index the rows of all B images stacked (``b H + row``); see :func:`_disk_segments`
    for the other fields. The ids of a segment are those of its runs of equal ids, and one
    sort of ``(owner, id)`` keys makes the sets distinct.
    """
    row_start = rows * ids.shape[-1]
    runs, pixel = _run_starts(ids, row_start + left, row_start + right)
    found = ids.reshape(-1).index_select(0, pixel)
    return _padded_sets(torch.repeat_interleave(owner, runs), found, count)
