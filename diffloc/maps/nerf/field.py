"""The radiance field: grid encoding, density and colour MLPs, per-image appearance codes.

``density(x)`` depends on position only; ``colour(x, d, image)`` adds the view direction
(real spherical harmonics up to degree 2) and a learnt appearance code of the image
(NeRF-W, Martin-Brualla et al. 2021), so that lighting that changes between runs is explained
by the code rather than by geometry. Normals are the normalised negative density gradient,
formed analytically in the same evaluation as the density. With ``background="learned"`` the
field also has a background colour (:meth:`RadianceField.background`) that rays which leave it
composite over (the sky outdoors).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import nn

from diffloc.checks import check_int_at_least, check_number, check_shape
from diffloc.maps.nerf.contraction import SceneNormalisation
from diffloc.maps.nerf.encodings import (
    HashGridEncoding,
    TriplaneEncoding,
    triplane_axis_resolutions,
)

__all__ = [
    "BACKGROUNDS",
    "ENCODINGS",
    "FieldConfig",
    "FieldOutputs",
    "RadianceField",
    "build_encoding",
    "sh_basis_deg2",
]


ENCODINGS = ("triplane", "hashgrid")
"""The position encodings of :class:`RadianceField`."""

BACKGROUNDS = ("none", "learned")
"""Background models of :class:`RadianceField`: none (rays that leave the field composite over
black) or a learnt colour of the image's appearance code."""


@dataclass
class FieldConfig:
    """Settings of :class:`RadianceField`.

    Attributes:
        encoding: ``"triplane"`` or ``"hashgrid"``.
        triplane_resolutions: plane resolution per tri-plane level (vertices per axis of a
            square level).
        triplane_aspect: exponent in [0, 1] of the box's extents that each level's vertices
            per axis follow at the same number of vertices per level
            (:func:`~diffloc.maps.nerf.encodings.triplane_axis_resolutions`): 0 square planes,
            1 cubic cells in the box (vertices proportional to the box's side lengths).
        triplane_channels: features per plane.
        hash_levels: hash-grid levels.
        hash_channels: features per level.
        hash_log2_table_size: log2 rows per level.
        hash_base_resolution: coarsest vertices per axis.
        hash_max_resolution: finest vertices per axis.
        init_std: encoding initialisation scale.
        hidden: width of both MLPs.
        geo_features: features the density MLP passes to the colour MLP.
        appearance_dim: length of the per-image appearance code (0: none).
        contracted: mip-NeRF 360 contraction (unbounded scenes).
        density_bias: added to the density logit before ``exp`` (start nearly empty).
        background: ``"none"`` or ``"learned"`` (:data:`BACKGROUNDS`): the colour a ray's
            remaining transmittance composites over, ``sigmoid(W a + b)`` of the image's
            appearance code ``a`` (its colour input, as for the colour MLP).
    """

    encoding: str = "triplane"
    triplane_resolutions: list[int] = dataclasses.field(default_factory=lambda: [64, 128, 256])
    triplane_aspect: float = 0.0
    triplane_channels: int = 8
    hash_levels: int = 12
    hash_channels: int = 2
    hash_log2_table_size: int = 17
    hash_base_resolution: int = 16
    hash_max_resolution: int = 512
    init_std: float = 0.1
    hidden: int = 64
    geo_features: int = 15
    appearance_dim: int = 8
    contracted: bool = False
    density_bias: float = -1.0
    background: str = "none"

    def __post_init__(self) -> None:
        if self.background not in BACKGROUNDS:
            raise ValueError(
                f"background must be one of {list(BACKGROUNDS)} (got {self.background!r})"
            )
        if self.encoding not in ENCODINGS:
            raise ValueError(
                f"encoding must be one of {list(ENCODINGS)} (unknown encoding {self.encoding!r})"
            )
        resolutions = self.triplane_resolutions
        if not resolutions or isinstance(resolutions, str | int):
            raise ValueError(f"triplane_resolutions must be a non-empty list, got {resolutions!r}")
        for value in resolutions:
            check_int_at_least(value, "triplane_resolutions", 2)
        for name in ("triplane_channels", "hash_levels", "hash_channels", "hidden"):
            check_int_at_least(getattr(self, name), name, 1)
        check_int_at_least(self.hash_log2_table_size, "hash_log2_table_size", 1)
        check_int_at_least(self.hash_base_resolution, "hash_base_resolution", 2)
        check_int_at_least(
            self.hash_max_resolution, "hash_max_resolution", self.hash_base_resolution
        )
        check_int_at_least(self.geo_features, "geo_features", 0)
        check_int_at_least(self.appearance_dim, "appearance_dim", 0)
        check_number(self.init_std, "init_std", 0.0, open_low=True)
        check_number(self.triplane_aspect, "triplane_aspect", 0.0, 1.0)
        check_number(self.density_bias, "density_bias")


@dataclass
class FieldOutputs:
    """Per-sample outputs: density (N,), rgb (N, 3), and normal (N, 3) when asked for."""

    density: torch.Tensor
    rgb: torch.Tensor
    normal: torch.Tensor | None


def build_encoding(
    config: FieldConfig, extent: torch.Tensor | None = None
) -> TriplaneEncoding | HashGridEncoding:
    """The grid encoding named by ``config.encoding``.

    Args:
        config: the settings.
        extent: (3,) side lengths of the box the cube spans (the tri-plane's per-axis vertex
            counts with ``triplane_aspect > 0``); ``None``: a cube.

    Raises:
        ValueError: an unknown encoding name.
    """
    if config.encoding == "triplane":
        sides = [1.0] * 3 if extent is None else [float(e) for e in extent]
        resolutions = triplane_axis_resolutions(
            config.triplane_resolutions, sides, config.triplane_aspect
        )
        return TriplaneEncoding(resolutions, config.triplane_channels, config.init_std)
    if config.encoding == "hashgrid":
        return HashGridEncoding(
            config.hash_levels,
            config.hash_channels,
            config.hash_log2_table_size,
            config.hash_base_resolution,
            config.hash_max_resolution,
            config.init_std,
        )
    raise ValueError(f"unknown encoding {config.encoding!r}; use 'triplane' or 'hashgrid'")


def sh_basis_deg2(directions: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics of degree <= 2 of (N, 3) unit vectors -> (N, 9)."""
    x, y, z = directions.unbind(-1)
    return torch.stack(
        (
            torch.full_like(x, 0.28209479177387814),
            0.4886025119029199 * y,
            0.4886025119029199 * z,
            0.4886025119029199 * x,
            1.0925484305920792 * x * y,
            1.0925484305920792 * y * z,
            0.31539156525252005 * (3 * z * z - 1),
            1.0925484305920792 * x * z,
            0.5462742152960396 * (x * x - y * y),
        ),
        dim=-1,
    )


def _mlp(inputs: int, hidden: int, outputs: int) -> nn.Sequential:
    # in place: the hidden layer's pre-activation is not needed by any backward
    return nn.Sequential(
        nn.Linear(inputs, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, outputs)
    )


class RadianceField(nn.Module):
    """Density and view-dependent colour of world points.

    Args:
        config: network settings.
        box_min: (3,) world lower corner of the submap box.
        box_max: (3,) upper corner.
        num_images: number of training images (appearance codes).
    """

    def __init__(
        self, config: FieldConfig, box_min: torch.Tensor, box_max: torch.Tensor, num_images: int
    ) -> None:
        super().__init__()
        self.config = config
        self.normalise = SceneNormalisation(box_min, box_max, config.contracted)
        self.encoding = build_encoding(config, 2 * self.normalise.half_extent)
        self.density_mlp = _mlp(self.encoding.out_dim, config.hidden, 1 + config.geo_features)
        colour_in = config.geo_features + 9 + config.appearance_dim
        self.colour_mlp = _mlp(colour_in, config.hidden, 3)
        self.appearance = nn.Embedding(max(num_images, 1), config.appearance_dim)
        nn.init.zeros_(self.appearance.weight)
        self.background_head: nn.Linear | None = None
        if config.background == "learned":
            self.background_head = nn.Linear(config.appearance_dim, 3)
            nn.init.zeros_(self.background_head.weight)
            nn.init.zeros_(self.background_head.bias)

    def background(self, appearance: torch.Tensor) -> torch.Tensor | None:
        """Background RGB (N, 3) in [0, 1] of rays of images with appearance codes
        (N, appearance_dim), ``None`` without a background model (``config.background``).
        Starts at grey (0.5) for every code."""
        if self.background_head is None:
            return None
        check_shape(appearance, f"N,{self.config.appearance_dim}", "appearance")
        return torch.sigmoid(self.background_head(appearance))

    def geometry(self, points_world: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density (N,) in 1/m (zero outside the field) and the geometry features
        (N, geo_features) the colour MLP reads, of (N, 3) world points."""
        check_shape(points_world, "N,3", "points_world")
        return self.geometry_in_cube(*self.normalise(points_world))

    def geometry_in_cube(
        self, xyz: torch.Tensor, inside: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`geometry` of points already normalised (``self.normalise``): (N, 3) cube
        points and their (N,) inside flags."""
        h = self.density_mlp(self.encoding(xyz))
        return self._density(h[:, 0], inside), h[:, 1:]

    def _density(self, output: torch.Tensor, inside: torch.Tensor) -> torch.Tensor:
        """Density (N,) from the density MLP's first output (N,): ``exp`` of the biased logit
        (clamped at 15), zero outside the field."""
        return torch.exp((output + self.config.density_bias).clamp(max=15.0)) * inside

    def density(self, points_world: torch.Tensor) -> torch.Tensor:
        """Volume density (N,) in 1/m of (N, 3) world points (zero outside the field)."""
        return self.geometry(points_world)[0]

    def geometry_and_normals(
        self, points_world: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`geometry` and the unit normals ``-grad(density) / |grad(density)|`` of (N, 3)
        world points in one evaluation.

        The density gradient is formed analytically (chain rule through the encoding's corner
        features, the ReLU MLP, ``exp`` and the normalisation), so the normals cost no second
        density evaluation, work without autograd, and back-propagate (the normal loss,
        Eq. 7) by first-order autograd only.

        Returns:
            ``(density, geo, normals)``: (N,), (N, geo_features) and (N, 3); the normal is zero
            where the gradient vanishes (outside a bounded field).
        """
        check_shape(points_world, "N,3", "points_world")
        xyz, inside = self.normalise(points_world)
        features, jacobian = self.encoding.forward_with_jacobian(xyz)
        first, second = self.density_mlp[0], self.density_mlp[2]
        hidden = first(features)
        h = second(torch.relu(hidden))
        density = self._density(h[:, 0], inside)
        d_logit = (second.weight[0] * (hidden > 0)) @ first.weight  # (N, features)
        grad_xyz = (d_logit[..., None] * jacobian).sum(dim=1)
        scale = density * (h[:, 0] + self.config.density_bias <= 15.0)  # the clamp's gradient
        grad = scale[:, None] * self.normalise.pullback(points_world, grad_xyz)
        return density, h[:, 1:], -grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-9)

    def normals(self, points_world: torch.Tensor) -> torch.Tensor:
        """Unit normals ``-grad(density) / |grad(density)|`` (N, 3) of (N, 3) world points.

        With grad enabled, :meth:`geometry_and_normals` (differentiable). Without, one
        first-order autograd pass of the density back to the points (no graph kept, no
        parameter gradients), which costs about half the analytic Jacobian when nothing
        needs differentiating (rendering).
        """
        if torch.is_grad_enabled():
            return self.geometry_and_normals(points_world)[2]
        with torch.enable_grad():
            x = points_world.detach().requires_grad_(True)
            (grad,) = torch.autograd.grad(self.density(x).sum(), x)
        return -grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-9)

    def colour(
        self, geo: torch.Tensor, directions: torch.Tensor, appearance: torch.Tensor
    ) -> torch.Tensor:
        """RGB (N, 3) in [0, 1] of samples with geometry features (N, geo_features) seen along
        unit directions (N, 3) in images with appearance codes (N, appearance_dim)."""
        check_shape(directions, "N,3", "directions")
        check_shape(appearance, f"N,{self.config.appearance_dim}", "appearance")
        features = torch.cat((geo, sh_basis_deg2(directions), appearance), dim=-1)
        return torch.sigmoid(self.colour_mlp(features))

    def forward(
        self,
        points_world: torch.Tensor,
        directions: torch.Tensor,
        appearance: torch.Tensor,
        with_normals: bool = False,
    ) -> FieldOutputs:
        """Evaluate the field (:meth:`geometry`, :meth:`colour` and :meth:`normals`).

        Args:
            points_world: (N, 3) sample positions.
            directions: (N, 3) unit ray directions.
            appearance: (N, appearance_dim) appearance codes of the samples' images.
            with_normals: also return unit normals (differentiable when grad is enabled).

        Returns:
            The per-sample :class:`FieldOutputs`.
        """
        normal = None
        if with_normals:
            density, geo, normal = self.geometry_and_normals(points_world)
        else:
            density, geo = self.geometry(points_world)
        return FieldOutputs(density, self.colour(geo, directions, appearance), normal)
