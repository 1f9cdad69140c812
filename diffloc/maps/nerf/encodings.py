"""Grid encodings of points in the normalised cube ``[-1, 1]^3``: tri-plane and hash grid.

Both interpolate learnable feature tables, with ``grid_sample`` where the table is a dense
grid and a fused weighted sum of the eight corner rows (:func:`trilinear_lookup`) where it is
hashed; both are twice differentiable in the positions. Explicit gathers
(:func:`trilinear_gather`, :func:`bilinear_gather`) serve as the slow reference of the fast
paths. ``forward_with_jacobian``
returns the features and their analytic derivatives with respect to the position from the
cell corners of one lookup: the rendered normal (the negative density gradient, Eq. 7) then
costs no second evaluation and no double backward, since the derivatives are ordinary
differentiable functions of the corner features and the fractional offsets. Vertex
convention is ``align_corners=True``: coordinate ``-1`` is vertex 0, ``+1`` vertex ``R - 1``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from diffloc.checks import check_number, check_shape

__all__ = [
    "HashGridEncoding",
    "TriplaneEncoding",
    "bilinear_gather",
    "multilinear",
    "multilinear_with_gradient",
    "trilinear_gather",
    "trilinear_lookup",
    "triplane_axis_resolutions",
]

# Spatial hash primes of Instant-NGP (Mueller et al. 2022), one per axis.
_PRIMES = (1, 2654435761, 805459861)


def _cell(
    coords: torch.Tensor, resolution: int | torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower vertex index and fractional offset of each coordinate on a grid of ``resolution``
    vertices per axis (an int, or a tensor of vertices per axis broadcastable to ``coords``).
    coords: (N, D) in [-1, 1] -> (N, D) int64 and (N, D) float."""
    u = (coords.clamp(-1.0, 1.0) + 1.0) * (0.5 * (resolution - 1))
    lower = torch.minimum(u.detach().floor(), torch.as_tensor(resolution - 2).to(u))
    return lower.long(), u - lower


def _corners(dims: int, device: torch.device) -> torch.Tensor:
    """(2**dims, dims) 0/1 offsets of a cell's corners: corner c is ``(c >> a) & 1`` along a."""
    return torch.tensor(
        [[(c >> a) & 1 for a in range(dims)] for c in range(2**dims)], device=device
    )


def multilinear(rows: torch.Tensor, frac: torch.Tensor) -> torch.Tensor:
    """Multilinear interpolation of cell corner features (corners first, so that each corner
    is a contiguous block).

    Args:
        rows: (2**D, ...) features at the corners (order of :func:`_corners`).
        frac: (D, ...) fractional offsets in the cell, in [0, 1], broadcastable to ``rows[0]``.

    Returns:
        (...) interpolated features.

    Example:
        >>> multilinear(torch.tensor([[0.0], [1.0], [2.0], [3.0]]), torch.tensor([[0.5], [0.5]]))
        tensor([1.5000])
    """
    for axis in reversed(range(len(frac))):  # the last axis is the corners' top bit
        half = len(rows) // 2
        lo, hi = rows[:half], rows[half:]
        rows = lo + frac[axis] * (hi - lo)
    return rows[0]


def multilinear_with_gradient(
    rows: torch.Tensor, frac: torch.Tensor, coords: torch.Tensor, resolution: int | torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`multilinear` and its derivative with respect to the coordinates in [-1, 1].

    Along each axis the derivative is the difference of the two faces of the cell,
    interpolated over the other axes, times the cells per coordinate unit.

    Args:
        rows: (2**D, ...) corner features.
        frac: (D, ...) fractional offsets in the cell.
        coords: (D, ...) the coordinates (zero derivative where they are clamped, beyond +-1).
        resolution: vertices per axis R (a coordinate step of 2 / (R - 1) crosses one cell),
            an int or a tensor broadcastable to ``coords`` (per-axis counts).

    Returns:
        ``(value, gradient)``: (...) and (D, ...).
    """
    slopes = [rows[0]] * len(frac)
    for axis in reversed(range(len(frac))):
        half = len(rows) // 2
        lo, diff = rows[:half], rows[half:] - rows[:half]
        slopes[axis] = multilinear(diff, frac[:axis])
        rows = lo + frac[axis] * diff
    scale = 0.5 * (resolution - 1) * ((coords >= -1.0) & (coords <= 1.0)).to(frac.dtype)
    return rows[0], torch.stack(slopes) * scale


def bilinear_gather(
    table: torch.Tensor, uv: torch.Tensor, resolution: int | tuple[int, int]
) -> torch.Tensor:
    """Bilinear interpolation of a feature plane stored row-major.

    Args:
        table: (R_j * R_i, C) features, vertex ``(i, j)`` (i along the first coordinate) at row
            ``j * R_i + i``.
        uv: (N, 2) coordinates in [-1, 1] (clamped).
        resolution: vertices ``(R_i, R_j)`` along the two coordinates, each >= 2; an int R
            for a square plane.

    Returns:
        (N, C) interpolated features.

    Example:
        >>> table = torch.arange(6.0)[:, None]  # 3 x 2 vertices, value 3 j + i
        >>> bilinear_gather(table, torch.tensor([[0.0, 0.0], [1.0, 1.0]]), (3, 2))[:, 0]
        tensor([2.5000, 5.0000])
    """
    check_shape(uv, "N,2", "uv")
    r_i, r_j = (resolution, resolution) if isinstance(resolution, int) else resolution
    if len(table) != r_i * r_j:
        raise ValueError(f"table has {len(table)} rows, a {r_i} x {r_j} plane needs {r_i * r_j}")
    lower, frac = _cell(uv, torch.tensor([r_i, r_j], dtype=uv.dtype, device=uv.device))
    vertex = lower[:, None] + _corners(2, uv.device)
    rows = table.index_select(0, (vertex[..., 1] * r_i + vertex[..., 0]).reshape(-1))
    return multilinear(rows.view(len(uv), 4, table.shape[1]).transpose(0, 1), frac.T[..., None])


def _vertex_index(vertex: torch.Tensor, resolution: int, table_size: int) -> torch.Tensor:
    """Row of each (N, 3) integer vertex: dense if the grid fits the table, else hashed (the
    hash modulo the table size; a mask where the size is a power of two, as the hash grid's
    tables are: the same rows, without an integer division per corner)."""
    if resolution**3 <= table_size:
        return (vertex[:, 2] * resolution + vertex[:, 1]) * resolution + vertex[:, 0]
    h = vertex[:, 0] * _PRIMES[0]
    h = torch.bitwise_xor(h, vertex[:, 1] * _PRIMES[1])
    h = torch.bitwise_xor(h, vertex[:, 2] * _PRIMES[2])
    if table_size & (table_size - 1) == 0:
        return torch.bitwise_and(h, table_size - 1)
    return torch.remainder(h, table_size)


def _cell_rows(lower: torch.Tensor, resolution: int, table_size: int) -> torch.Tensor:
    """Rows (N, 8) of the eight corners (order of :func:`_corners`) of the cells with lower
    vertices (3, N) (points last): :func:`_vertex_index` of each corner, formed per axis (two
    vertex terms per axis, then their eight sums / exclusive ors, along the points)."""
    ends = lower[:, None] + torch.arange(2, device=lower.device)[:, None]  # (3, 2, N)
    if resolution**3 <= table_size:
        x, y, z = ends[0], ends[1] * resolution, ends[2] * resolution**2
        rows = (z[:, None] + y[None])[:, :, None] + x[None, None]
    else:
        x, y, z = (ends[a] * prime for a, prime in enumerate(_PRIMES))
        rows = (z[:, None] ^ y[None])[:, :, None] ^ x[None, None]
        if table_size & (table_size - 1) == 0:
            rows = torch.bitwise_and(rows, table_size - 1)
        else:
            rows = torch.remainder(rows, table_size)
    return rows.reshape(8, -1).T.contiguous()


def _corner_weights(frac: torch.Tensor) -> torch.Tensor:
    """Trilinear weights (N, 8) of the corners (order of :func:`_corners`) of points at
    fractional offsets (3, N) in their cells: the product over the axes of ``1 - f`` or ``f``."""
    f = torch.stack((1 - frac, frac), dim=1)  # (3, 2, N)
    weights = (f[2, :, None] * f[1, None])[:, :, None] * f[0, None, None]
    return weights.reshape(8, -1).T.contiguous()


class _WeightedRows(torch.autograd.Function):
    """``out[n] = sum_c weights[n, c] table[rows[n, c]]``: (T, C), (N, K) int64, (N, K) ->
    (N, C). The forward is ``embedding_bag``'s fused weighted sum; the backward one
    ``index_add_`` for the table (``embedding_bag``'s own backward with per-sample weights
    costs ~4x more on CPU) and a gather for the weights, both differentiable."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, rows: torch.Tensor, weights: torch.Tensor):
        ctx.save_for_backward(table, rows, weights)
        return F.embedding_bag(rows, table, per_sample_weights=weights, mode="sum")

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        table, rows, weights = ctx.saved_tensors
        grad_table = grad_weights = None
        if ctx.needs_input_grad[0]:
            spread = (weights[..., None] * grad[:, None]).reshape(-1, table.shape[1])
            grad_table = torch.zeros_like(table).index_add_(0, rows.reshape(-1), spread)
        if ctx.needs_input_grad[2]:
            grad_weights = (table[rows] * grad[:, None]).sum(-1)
        return grad_table, None, grad_weights


def trilinear_lookup(table: torch.Tensor, xyz: torch.Tensor, resolution: int) -> torch.Tensor:
    """:func:`trilinear_gather` as one fused weighted sum of the eight corner rows
    (:class:`_WeightedRows`): the same interpolation, without the (8, N, C) corner tensor and
    the seven element-wise lerps of :func:`multilinear` and their backward.

    Args:
        table: (T, C) features, indexed as in :func:`trilinear_gather`.
        xyz: (N, 3) coordinates in [-1, 1] (clamped).
        resolution: R >= 2 vertices per axis.

    Returns:
        (N, C) interpolated features.

    Example:
        >>> table = torch.arange(8.0)[:, None]  # 2^3 vertices, value i + 2 j + 4 k
        >>> trilinear_lookup(table, torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, 1.0]]), 2)[:, 0]
        tensor([3.5000, 5.0000])
    """
    check_shape(xyz, "N,3", "xyz")
    # points last: the broadcast products and hashes below then run along the points (an
    # inner axis of 2 corners is ~10x slower on CPU)
    lower, frac = _cell(xyz.T.contiguous(), resolution)
    rows = _cell_rows(lower, resolution, len(table))
    return _WeightedRows.apply(table, rows, _corner_weights(frac))


def trilinear_gather(table: torch.Tensor, xyz: torch.Tensor, resolution: int) -> torch.Tensor:
    """Trilinear interpolation of one hash-grid level.

    Args:
        table: (T, C) features. A grid of ``R^3 <= T`` vertices is indexed densely
            (vertex ``(i, j, k)`` at row ``(k R + j) R + i``), a larger one by the spatial hash.
        xyz: (N, 3) coordinates in [-1, 1] (clamped).
        resolution: R >= 2 vertices per axis.

    Returns:
        (N, C) interpolated features.
    """
    check_shape(xyz, "N,3", "xyz")
    return multilinear(*_trilinear_corners(table, xyz, resolution))


def _trilinear_corners(
    table: torch.Tensor, xyz: torch.Tensor, resolution: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Corner rows (8, N, C) and fractional offsets (3, N, 1) of (N, 3) points in one level."""
    lower, frac = _cell(xyz, resolution)
    vertex = (lower[:, None] + _corners(3, xyz.device)).reshape(-1, 3)
    rows = table.index_select(0, _vertex_index(vertex, resolution, len(table)))
    return rows.view(len(xyz), 8, table.shape[1]).transpose(0, 1), frac.T[..., None]


def _grid_sample(
    volume: torch.Tensor, coords: torch.Tensor, mode: str = "bilinear"
) -> torch.Tensor:
    """``grid_sample`` with the gathers' conventions: volume (B, C, *R) with the first
    coordinate along the last axis, coords (B, N, D) -> (B, N, C)."""
    grid = coords.clamp(-1.0, 1.0).reshape(
        len(coords), -1, *([1] * (coords.shape[-1] - 1)), coords.shape[-1]
    )
    out = F.grid_sample(volume, grid, mode=mode, padding_mode="border", align_corners=True)
    return out.reshape(len(coords), volume.shape[1], -1).transpose(1, 2)


def _product(planes: torch.Tensor | Sequence[torch.Tensor]) -> torch.Tensor:
    """Product of the three planes' features (3, ...) -> (...), as two multiplications: the
    backward of ``prod`` tests for zeros and divides, about 8 % of a training step."""
    return planes[0] * planes[1] * planes[2]


def triplane_axis_resolutions(
    resolutions: Sequence[int], extent: Sequence[float], aspect: float
) -> list[tuple[int, int, int]]:
    """Vertices per axis of each tri-plane level for a box of ``extent``: axis ``a`` gets
    ``R w_a / g`` vertices (rounded, at least 2) with ``w_a = extent_a ** aspect`` and ``g``
    such that the three planes hold ``3 R^2`` vertices, as a square level of ``R`` does.

    ``aspect`` 0 gives square planes (``R`` on every axis); 1 makes the vertex counts
    proportional to the extents, so the cells are cubes in the box; values between
    interpolate geometrically.

    Args:
        resolutions: ``R`` of each level.
        extent: (3,) the box's side lengths (any unit; only their ratios matter).
        aspect: exponent in [0, 1].

    Returns:
        ``(R_x, R_y, R_z)`` per level.

    Raises:
        ValueError: an extent that is not positive or an aspect outside [0, 1].

    Example:
        >>> triplane_axis_resolutions([64], [4.0, 4.0, 1.0], 1.0)
        [(91, 91, 23)]
    """
    check_number(aspect, "triplane_aspect", 0.0, 1.0)
    if len(extent) != 3 or not all(math.isfinite(e) and e > 0 for e in extent):
        raise ValueError(f"the box extent must be three positive lengths, got {list(extent)}")
    w = [float(e) ** aspect for e in extent]
    g = math.sqrt((w[0] * w[1] + w[0] * w[2] + w[1] * w[2]) / 3.0)
    return [tuple(max(2, round(r * wa / g)) for wa in w) for r in resolutions]


class TriplaneEncoding(nn.Module):
    """Multi-resolution tri-plane (EG3D / K-Planes style): three axis-aligned feature planes
    per resolution (xy, xz, yz), the per-plane features multiplied (K-Planes' Hadamard
    product) and the levels concatenated. Interpolation uses ``grid_sample`` (twice
    differentiable); :func:`bilinear_gather` is its slow reference.

    A level is square (``R`` vertices on every axis) or has its own count per axis
    ``(R_x, R_y, R_z)`` (:func:`triplane_axis_resolutions`); plane ``(a, b)`` then has
    ``R_a x R_b`` vertices. Plane ``p`` of level ``l`` is the parameter ``planes.{3 l + p}``
    of shape (channels, R_b, R_a); fields saved with a level's three planes stacked in one
    (3, channels, R, R) parameter ``planes.{l}`` load into it unchanged.

    Args:
        resolutions: each level's ``R`` or ``(R_x, R_y, R_z)``, e.g. ``(64, 128, 256)``.
        channels: features per plane.
        init_std: features start at ``1 + N(0, init_std)`` (the product starts near one).
    """

    PAIRS = ((0, 1), (0, 2), (1, 2))

    def __init__(
        self, resolutions: Sequence[int | Sequence[int]], channels: int, init_std: float
    ) -> None:
        super().__init__()
        self.resolutions = tuple(
            (int(r),) * 3 if isinstance(r, int) else tuple(int(v) for v in r) for r in resolutions
        )
        for r in self.resolutions:
            if len(r) != 3 or min(r) < 2:
                raise ValueError(f"a tri-plane level needs >= 2 vertices on 3 axes, got {r}")
        self.planes = nn.ParameterList(
            nn.Parameter(1.0 + init_std * torch.randn(channels, r[b], r[a]))
            for r in self.resolutions
            for a, b in self.PAIRS
        )
        self.out_dim = channels * len(self.resolutions)
        # (3, 6): axis a of the point <- coordinate k of plane p (column 2 p + k)
        pair_axes = torch.zeros(3, 2 * len(self.PAIRS))
        for plane, pair in enumerate(self.PAIRS):
            for k, axis in enumerate(pair):
                pair_axes[axis, 2 * plane + k] = 1.0
        self.register_buffer("_pair_axes", pair_axes, persistent=False)
        self.register_load_state_dict_pre_hook(TriplaneEncoding._split_stacked_planes)

    def _split_stacked_planes(self, state_dict: dict, prefix: str, *args) -> None:
        """Load hook: a level saved as one stacked (3, C, R, R) ``planes.{l}`` (fields exported
        before per-axis resolutions) becomes its three planes ``planes.{3 l + p}``."""
        key = f"{prefix}planes."
        stacked = [k for k, v in state_dict.items() if k.startswith(key) and v.dim() == 4]
        levels = {int(k[len(key) :]): state_dict.pop(k) for k in stacked}  # all out, then in
        for level, value in levels.items():
            for plane in range(len(self.PAIRS)):
                state_dict[f"{key}{len(self.PAIRS) * level + plane}"] = value[plane]

    def _levels(self) -> Iterator[tuple[tuple[int, ...], list[nn.Parameter]]]:
        """(per-axis resolution, the level's three planes) of each level."""
        n = len(self.PAIRS)
        for level, r in enumerate(self.resolutions):
            yield r, [self.planes[n * level + p] for p in range(n)]

    def forward(self, xyz: torch.Tensor) -> torch.Tensor:
        """Features of (N, 3) points in [-1, 1]^3 -> (N, out_dim)."""
        check_shape(xyz, "N,3", "xyz")
        coords = [xyz[:, pair][None] for pair in self.PAIRS]
        return torch.cat(
            [
                _product([_grid_sample(p[None], c)[0] for p, c in zip(planes, coords, strict=True)])
                for _, planes in self._levels()
            ],
            dim=-1,
        )

    def forward_with_jacobian(self, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Features (N, out_dim) of (N, 3) points in [-1, 1]^3 and their derivatives
        (N, out_dim, 3) with respect to the points, from the four corners of each point's cell
        on each plane (``grid_sample`` at the vertices, nearest): one lookup, no autograd."""
        check_shape(xyz, "N,3", "xyz")
        n = len(xyz)
        coords = torch.stack([xyz[:, pair] for pair in self.PAIRS])  # (3, N, 2)
        at = coords.permute(2, 0, 1)[:, :, None]  # (2, 3, 1, N): per plane axis
        corners = _corners(2, xyz.device)[:, None]
        features, jacobians = [], []
        for r, planes in self._levels():
            c = planes[0].shape[0]
            res = torch.tensor(  # (3, 2): vertices along each plane's two coordinates
                [[r[a], r[b]] for a, b in self.PAIRS], dtype=xyz.dtype, device=xyz.device
            )
            lower, frac = _cell(coords, res[:, None])
            rows = []
            for p, plane in enumerate(planes):
                vertex = (lower[p] + corners).to(xyz.dtype) * (2 / (res[p] - 1)) - 1  # (4, N, 2)
                rows.append(_grid_sample(plane[None], vertex.reshape(1, 4 * n, 2), "nearest")[0])
            rows = torch.stack(rows).reshape(3, 4, n, c).permute(1, 0, 3, 2)  # (4, 3, C, N)
            scale = res.T[:, :, None, None]  # (2, 3, 1, 1): vertices along each plane axis
            value, slope = multilinear_with_gradient(
                rows, frac.permute(2, 0, 1)[:, :, None], at, scale
            )
            # product rule: d(v0 v1 v2) = sum_p (prod_{q != p} v_q) dv_p, dv_p on its pair
            others = torch.stack((value[1] * value[2], value[0] * value[2], value[0] * value[1]))
            terms = (others * slope).transpose(0, 1).reshape(6, -1)  # row 2 p + k
            jacobians.append((self._pair_axes.to(terms.dtype) @ terms).reshape(3, c, n))
            features.append(_product(value))  # (C, N)
        return torch.cat(features).T, torch.cat(jacobians, dim=1).permute(2, 1, 0)

    def forward_reference(self, xyz: torch.Tensor) -> torch.Tensor:
        """:meth:`forward` with explicit gathers (slow reference for tests)."""
        levels = []
        for r, planes in self._levels():
            feature = 1.0
            for plane, (a, b) in zip(planes, self.PAIRS, strict=True):
                table = plane.permute(1, 2, 0).reshape(r[a] * r[b], -1)
                feature = feature * bilinear_gather(table, xyz[:, (a, b)], (r[a], r[b]))
            levels.append(feature)
        return torch.cat(levels, dim=-1)


class HashGridEncoding(nn.Module):
    """Multi-resolution hash grid (Instant-NGP): ``levels`` grids from ``base_resolution`` to
    ``max_resolution`` vertices per axis in geometric progression, each a table of
    ``2**log2_table_size`` rows of ``channels`` features (coarse levels that fit are dense).

    Args:
        levels: number of levels L.
        channels: features per level F.
        log2_table_size: log2 of the rows per level T.
        base_resolution: vertices per axis of the coarsest level.
        max_resolution: vertices per axis of the finest level.
        init_std: features start as ``U(-init_std, init_std)``.
    """

    def __init__(
        self,
        levels: int,
        channels: int,
        log2_table_size: int,
        base_resolution: int,
        max_resolution: int,
        init_std: float,
    ) -> None:
        super().__init__()
        growth = math.exp(math.log(max_resolution / base_resolution) / max(levels - 1, 1))
        self.resolutions = tuple(
            max(2, int(math.floor(base_resolution * growth**level))) for level in range(levels)
        )
        size = 2**log2_table_size
        self.tables = nn.ParameterList(
            nn.Parameter((torch.rand(min(size, r**3), channels) * 2 - 1) * init_std)
            for r in self.resolutions
        )
        self.table_size = size
        self.out_dim = channels * levels

    def forward(self, xyz: torch.Tensor) -> torch.Tensor:
        """Features of (N, 3) points in [-1, 1]^3 -> (N, out_dim). Dense levels interpolate
        with ``grid_sample``, hashed ones with :func:`trilinear_lookup`."""
        check_shape(xyz, "N,3", "xyz")
        levels = []
        for table, r in zip(self.tables, self.resolutions, strict=True):
            if len(table) == r**3:
                volume = table.T.reshape(1, -1, r, r, r)
                levels.append(_grid_sample(volume, xyz[None])[0])
            else:
                levels.append(trilinear_lookup(table, xyz, r))
        return torch.cat(levels, dim=-1)

    def forward_with_jacobian(self, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Features (N, out_dim) of (N, 3) points in [-1, 1]^3 and their derivatives
        (N, out_dim, 3) with respect to the points, from each level's eight cell corners
        (gathers on every level): one lookup, no autograd."""
        check_shape(xyz, "N,3", "xyz")
        features, jacobians = [], []
        for table, r in zip(self.tables, self.resolutions, strict=True):
            rows, frac = _trilinear_corners(table, xyz, r)
            value, slope = multilinear_with_gradient(rows, frac, xyz.T[..., None], r)
            features.append(value)
            jacobians.append(slope.permute(1, 2, 0))
        return torch.cat(features, dim=-1), torch.cat(jacobians, dim=1)

    def forward_reference(self, xyz: torch.Tensor) -> torch.Tensor:
        """:meth:`forward` with explicit gathers on every level (slow reference for tests)."""
        pairs = zip(self.tables, self.resolutions, strict=True)
        return torch.cat([trilinear_gather(table, xyz, r) for table, r in pairs], dim=-1)
