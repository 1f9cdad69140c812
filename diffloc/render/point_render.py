"""Hard point splatting: RGB-D renders of coloured point maps (seed 2 Sec. III-D1).

:func:`render_points` draws square point splats (RGB-D, ids, mask) with the sizes of
:class:`~diffloc.render.point_sizes.PointSizes`: a fixed size, the inverse-depth size of
Eq. 2, or the multi-pass scheme with a few fixed sizes merged by nearest depth.

A point of integer size ``k`` covers the ``k x k`` pixels whose centres lie in the square of
side ``k`` centred on its projection (OpenGL point rasterisation). The keys of each pass (size
level, :mod:`~diffloc.render.zbuffer`) are scattered once into an "anchor" image (top-left
pixel of each splat); the squares are filled with separable sliding-window minima, evaluated
for all passes together from the largest size down, and the minimum merges the passes by
nearest depth. The cost is one scatter per point plus a few image-sized operations per pass,
independent of the splat area. Camera and bad-input rules: :mod:`~diffloc.render.view`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from diffloc.checks import ShapeError, check_shape
from diffloc.geometry.camera import MIN_DEPTH, PinholeCamera
from diffloc.render.point_sizes import PointSizes
from diffloc.render.screen_space import ScreenSpaceVisibility, hide_enclosed
from diffloc.render.view import _check_camera, _check_map_size, _check_poses, _View, _views
from diffloc.render.zbuffer import _CHUNK, _empty_keys, _pack_keys, _unpack_keys

__all__ = ["PointRender", "render_points", "see_through_fraction"]


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


def _gather_channels_first(values: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) rows of (N, C) ``values`` picked by (B, H, W) ``ids`` (-1 reads row 0)."""
    channels = values.shape[1]
    batch, height, width = ids.shape
    offsets = torch.arange(channels, device=ids.device).view(1, channels, 1, 1)
    flat = ids.clamp_min(0)[:, None] * channels + offsets
    if values.numel() == 0:
        return torch.zeros(flat.shape, dtype=values.dtype, device=values.device)
    return values.reshape(-1).index_select(0, flat.view(-1)).view(flat.shape)


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
    visibility: ScreenSpaceVisibility | None = None,
) -> PointRender:
    """Render a coloured point cloud as square splats with a z-buffer (seed 2 Sec. III-D1).

    The splat size of each point follows ``sizes`` (default: 1 pixel): fixed, per-point inverse
    depth (Eq. 2) or the multi-pass scheme; see :class:`PointSizes`. Splats are flat: every
    pixel of a splat gets the point's depth; the nearest splat wins (ties: lower index).
    With ``visibility``, pixels that nearer splats enclose in the image (see-through gaps and
    small holes) then take that nearer surface's point
    (:func:`~diffloc.render.screen_space.hide_enclosed`).

    Args:
        points: (N, 3) points, world frame (metres); rows with NaN/inf are culled.
        colors: (N, 3) colours in [0, 1].
        T_wc: (B, 4, 4) camera-to-world poses.
        camera: one camera or a batch of ``B`` (same image size); distortion allowed.
        sizes: splat sizes.
        visibility: the screen-space visibility filter (default: none).

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
    keys = torch.stack(keys)
    if visibility is not None:
        keys = hide_enclosed(keys, visibility)
    ids, depth = _unpack_keys(keys)
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
