"""Storey aliases: is a pose found in a rendered map explained as well on another floor?

Buildings repeat themselves from floor to floor, and a query can match a database render of
the wrong storey well: the pose found then has the right x, y and heading, one storey height
above or below the truth (indoor seed 0, TLS cloud, ``query_same`` frame 20: 2.98 m and 0.6 deg
off, 227 inliers). The rival test of the validation cannot refuse it when no render of the
other storey was retrieved. A rendered map can be rendered anywhere, so the alternative can be
tried directly: render the map at the pose found and at the same pose moved to every other
floor (the floors of the map's render poses, :func:`floor_heights`), match the query against
each render and solve PnP (:func:`~diffloc.reloc.rerender.rerender_candidate`). The pose is a
storey alias when a render on another floor yields a pose at least ``min_distance_m`` from the
pose found with at least ``ratio`` times the inliers of the render at the pose: the
validation's rival rule, applied to two renders made alike (:func:`is_storey_alias`).

Usage::

    heights = floor_heights(render_T_wc, floor_index)
    evidence = storey_alias_evidence(rgbd_map, T_wc, heights, view, networks, config)
    alias = is_storey_alias(evidence, min_distance_m=1.0, ratio=1.0)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from diffloc.checks import check_shape
from diffloc.crossmodal.synthesize import RGBDMap
from diffloc.features.local import Features, XFeatExtractor
from diffloc.features.matching import LighterGlueMatcher
from diffloc.geometry.camera import PinholeCamera
from diffloc.reloc.rendered import RenderedCandidate, RenderedLocalizerConfig
from diffloc.reloc.rerender import rerender_candidate

__all__ = [
    "AliasEvidence",
    "alias_poses",
    "floor_heights",
    "is_storey_alias",
    "storey_alias_evidence",
]


def floor_heights(T_wc: torch.Tensor, floor_index: torch.Tensor) -> torch.Tensor:
    """(F,) float64 median camera height of each floor's render poses, lowest first.

    Args:
        T_wc: (M, 4, 4) render poses (camera-to-world, z up).
        floor_index: (M,) int64 floor of each pose; negative: a pose on no floor (e.g. a
            trajectory sample), ignored.

    Raises:
        ShapeError: wrong shapes.

    Example:
        >>> T = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
        >>> T[:, 2, 3] = torch.tensor([4.5, 1.5, 1.6, 9.0], dtype=torch.float64)
        >>> floor_heights(T, torch.tensor([1, 0, 0, -1])).tolist()
        [1.55, 4.5]
    """
    check_shape(T_wc, "M,4,4", "T_wc")
    check_shape(floor_index, f"{T_wc.shape[0]}", "floor_index")
    z = T_wc[:, 2, 3].to(torch.float64).numpy()
    index = floor_index.numpy()
    floors = np.unique(index[index >= 0])
    # numpy's median (torch's takes the lower middle value of an even count)
    heights = [float(np.median(z[index == f])) for f in floors]
    return torch.sort(torch.tensor(heights, dtype=torch.float64)).values


def alias_poses(T_wc: torch.Tensor, heights: torch.Tensor) -> torch.Tensor:
    """(F - 1, 4, 4) ``T_wc`` moved vertically by the height difference from its nearest floor
    to each other floor (heading and x, y kept).

    Example:
        >>> T = torch.eye(4, dtype=torch.float64)
        >>> T[2, 3] = 1.4
        >>> alias_poses(T, torch.tensor([1.5, 4.5, 7.5], dtype=torch.float64))[:, 2, 3].tolist()
        [4.4, 7.4]
    """
    check_shape(T_wc, "4,4", "T_wc")
    check_shape(heights, "F", "heights")
    nearest = int(torch.argmin((heights - T_wc[2, 3]).abs()))
    others = torch.cat([heights[:nearest], heights[nearest + 1 :]])
    moved = T_wc.to(torch.float64).repeat(len(others), 1, 1)
    moved[:, 2, 3] += others - heights[nearest]
    return moved


@dataclass(frozen=True)
class AliasEvidence:
    """The renders at a pose found and at its storey aliases, matched with the query.

    Attributes:
        own_inliers: PnP inliers against the render at the pose (0: no pose; -1: not rendered,
            the map has one floor).
        alias_inliers: (F - 1,) PnP inliers against each alias render (0: no pose).
        alias_distance_m: (F - 1,) distance of each alias render's pose from the pose found
            (NaN: no pose).
    """

    own_inliers: int
    alias_inliers: tuple[int, ...]
    alias_distance_m: tuple[float, ...]


def is_storey_alias(evidence: AliasEvidence, min_distance_m: float, ratio: float) -> bool:
    """Whether an alias render gives a pose at least ``min_distance_m`` away with at least
    ``ratio`` times the inliers of the render at the pose (``task.storey_alias.ratio``: 1.0,
    the other floor explains the query at least as well).

    Example:
        >>> alias, weak = AliasEvidence(250, (445,), (2.96,)), AliasEvidence(250, (90,), (3.0,))
        >>> is_storey_alias(alias, 1.0, 1.0), is_storey_alias(weak, 1.0, 1.0)
        (True, False)
        >>> is_storey_alias(AliasEvidence(250, (400,), (0.1,)), 1.0, 1.0)  # back at the pose
        False
    """
    return any(
        distance >= min_distance_m and inliers >= ratio * evidence.own_inliers
        for inliers, distance in zip(evidence.alias_inliers, evidence.alias_distance_m, strict=True)
        if inliers > 0
    )


def _inliers_at(
    T_wc: torch.Tensor,
    rgbd_map: RGBDMap,
    render_camera: PinholeCamera,
    view: tuple[torch.Tensor, Features, PinholeCamera],
    networks: tuple[XFeatExtractor, LighterGlueMatcher],
    config: RenderedLocalizerConfig,
) -> RenderedCandidate:
    image, query, camera = view
    generator = torch.Generator().manual_seed(config.seed)
    return rerender_candidate(
        rgbd_map,
        T_wc,
        render_camera,
        image,
        query,
        camera,
        networks,
        config,
        generator,
        photometric=False,  # the test compares inliers only
    ).candidate


def storey_alias_evidence(
    rgbd_map: RGBDMap,
    T_wc: torch.Tensor,
    heights: torch.Tensor,
    render_camera: PinholeCamera,
    view: tuple[torch.Tensor, Features, PinholeCamera],
    networks: tuple[XFeatExtractor, LighterGlueMatcher],
    config: RenderedLocalizerConfig,
) -> AliasEvidence:
    """Render ``rgbd_map`` at ``T_wc`` and at its :func:`alias_poses`, match the query against
    each render and solve PnP (the localiser's XFeat, LighterGlue and PnP).

    Args:
        rgbd_map: the map.
        T_wc: (4, 4) the pose found.
        heights: (F,) the map's floor heights (:func:`floor_heights`).
        render_camera: the renders' camera (the database's).
        view: ``(image (3, H, W), features, camera)`` of the query.
        networks: the localiser's ``(extractor, matcher)``.
        config: the localiser's settings (matching, PnP; ``seed`` seeds RANSAC).
    """
    aliases = alias_poses(T_wc, heights)
    if len(aliases) == 0:  # one floor: nothing to compare with, nothing rendered
        return AliasEvidence(-1, (), ())
    own = _inliers_at(T_wc, rgbd_map, render_camera, view, networks, config)
    inliers, distances = [], []
    for T_alias in aliases:
        cand = _inliers_at(T_alias, rgbd_map, render_camera, view, networks, config)
        inliers.append(cand.num_inliers if cand.success else 0)
        moved = torch.linalg.vector_norm(cand.T_wc[:3, 3] - T_wc[:3, 3].to(cand.T_wc.dtype))
        distances.append(float(moved) if cand.success else float("nan"))
    return AliasEvidence(own.num_inliers if own.success else 0, tuple(inliers), tuple(distances))
