"""The maps a localised query is refined against: a coloured cloud or radiance-field submaps.

Both answer the two questions :func:`~diffloc.optim.render_refine.query.refine_query` asks of
a map (:class:`QueryMaps`): which of its parts serves a query (:meth:`QueryMaps.serving`, from
the query's *localised* pose, what a user has) and the differentiable map of that part for
one query at its start pose (:meth:`QueryMaps.model`):

- :class:`CloudMaps`: a coloured point cloud thinned to one point per ``spacing_m`` cell and
  cropped to each query's view, soft-splatted (:func:`point_cloud_map`); one part, index 0;
- :class:`FieldSubmaps`: trained radiance-field submaps, a query served as ``map=nerf`` serves
  a render pose (the submap whose core mapping frames have the largest affinity to it), its
  appearance code fitted at the start pose (:func:`fit_query_appearance`, NeRF-W test-time
  fit) before the refinement; a submap without a field serves no query (index -1).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection
from typing import Protocol

import torch

from diffloc.checks import check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.maps.nerf.field import RadianceField
from diffloc.maps.nerf.sampler import DensityGrid
from diffloc.maps.nerf.submaps import Submap, SubmapConfig, serving_submap
from diffloc.optim.render_refine.linearization import DifferentiableMap
from diffloc.optim.render_refine.point_cloud import crop_to_view, point_cloud_map
from diffloc.optim.render_refine.radiance_field import fit_query_appearance, radiance_field_map

__all__ = ["NO_MAP", "CloudMaps", "FieldSubmaps", "QueryMaps"]

NO_MAP = -1
"""The serving index of a query no part of the map can serve."""


class QueryMaps(Protocol):
    """A map split into parts, each query refined against the part serving it."""

    def serving(self, T_wc: torch.Tensor) -> list[int]:
        """(B, 4, 4) localised poses -> the part serving each (:data:`NO_MAP`: none)."""
        ...

    def model(
        self, served: int, T_wc: torch.Tensor, image: torch.Tensor, camera: PinholeCamera
    ) -> tuple[DifferentiableMap, dict[str, float]]:
        """Part ``served`` as a differentiable map for one query: ``image`` (1, 3, H, W) at
        ``camera``'s size seen from ``T_wc`` (1, 4, 4); also a record of how it was made."""
        ...


class CloudMaps:
    """A coloured cloud, thinned once and cropped to each query's view (one part, index 0).

    Args:
        points: (N, 3) world points.
        colours: (N, 3) colours in [0, 1].
        spacing_m: the cloud is thinned to the first point of every cell of this size; each
            splat's world radius is half of it.
        max_depth_m: points farther from a query's start pose are not rendered.

    Example:
        >>> cloud = CloudMaps(torch.rand(50, 3), torch.rand(50, 3), 0.5, 8.0)
        >>> len(cloud.points) <= 8, cloud.serving(torch.eye(4)[None].repeat(2, 1, 1))
        (True, [0, 0])
    """

    def __init__(
        self, points: torch.Tensor, colours: torch.Tensor, spacing_m: float, max_depth_m: float
    ) -> None:
        check_shape(points, "N,3", "points")
        check_shape(colours, f"{len(points)},3", "colours")
        _, inverse = torch.unique(torch.floor(points / spacing_m), dim=0, return_inverse=True)
        order = torch.arange(len(points))
        first = torch.full((int(inverse.max()) + 1,), len(points)).scatter_reduce(
            0, inverse, order, "amin"
        )
        first = first.sort().values
        self.points, self.colours = points[first].double(), colours[first].double()
        self.spacing_m, self.max_depth_m = spacing_m, max_depth_m

    def serving(self, T_wc: torch.Tensor) -> list[int]:
        """(B, 4, 4) poses -> 0 each (the cloud is one part)."""
        return [0] * len(T_wc)

    def model(
        self, served: int, T_wc: torch.Tensor, image: torch.Tensor, camera: PinholeCamera
    ) -> tuple[DifferentiableMap, dict[str, float]]:
        """The points within ``max_depth_m`` of the view of ``T_wc``, soft-splatted."""
        keep = crop_to_view(self.points, T_wc, camera, self.max_depth_m)
        cloud = point_cloud_map(self.points[keep], self.colours[keep], self.spacing_m / 2)
        return cloud, {"points": int(len(keep))}


FieldLoader = Callable[[int], tuple[RadianceField, DensityGrid]]
"""Submap index -> its trained field and density grid."""


class FieldSubmaps:
    """Trained radiance-field submaps, each query served by one (module doc).

    Args:
        submaps: the clustering of the mapping trajectory.
        config: its settings (the affinity scales that pick the serving submap).
        mapping_T_wc: (N, 4, 4) the mapping poses the submaps index.
        load: submap index -> its field and grid (called once per submap, on first use).
        available: the submaps that have a field; a query another submap serves gets
            :data:`NO_MAP`.
        fit_steps: Adam steps of each query's appearance-code fit.
    """

    def __init__(
        self,
        submaps: list[Submap],
        config: SubmapConfig,
        mapping_T_wc: torch.Tensor,
        load: FieldLoader,
        available: Collection[int],
        fit_steps: int = 60,
    ) -> None:
        check_shape(mapping_T_wc, "N,4,4", "mapping_T_wc")
        self.submaps, self.config = submaps, config
        self.mapping_T_wc = mapping_T_wc.double()
        self.available = set(available)
        self.fit_steps = fit_steps
        self._load = load
        self._fields: dict[int, tuple[RadianceField, DensityGrid]] = {}

    def serving(self, T_wc: torch.Tensor) -> list[int]:
        """(B, 4, 4) poses -> the submap serving each (largest core-frame affinity), or
        :data:`NO_MAP` where that submap has no field."""
        served = serving_submap(T_wc.double(), self.submaps, self.mapping_T_wc, self.config)
        return [k if k in self.available else NO_MAP for k in served.tolist()]

    def field(self, k: int) -> tuple[RadianceField, DensityGrid]:
        """Submap ``k``'s field (frozen) and density grid, loaded once."""
        if k not in self._fields:
            field, grid = self._load(k)
            field.eval().requires_grad_(False)
            self._fields[k] = (field, grid)
        return self._fields[k]

    def model(
        self, served: int, T_wc: torch.Tensor, image: torch.Tensor, camera: PinholeCamera
    ) -> tuple[DifferentiableMap, dict[str, float]]:
        """Submap ``served``'s field with the query's appearance code fitted at ``T_wc``; the
        record holds the submap and the fit's CPU ms."""
        field, grid = self.field(served)
        cpu = time.process_time()
        code = fit_query_appearance(
            field, grid, image.float(), T_wc.float(), camera, steps=self.fit_steps
        )
        fit_ms = 1e3 * (time.process_time() - cpu)
        return radiance_field_map(field, grid, code), {"submap": served, "fit_cpu_ms": fit_ms}
