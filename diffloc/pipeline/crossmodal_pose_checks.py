"""Settings of the checks ``diffloc task=crossmodal`` runs on the poses a rendered map gave.

A rendered map can be rendered at any pose, so a pose found can be checked against renders
made for it rather than against the database's alone: ``task.rerender``
(:class:`RerenderConfig`, :mod:`diffloc.pipeline.crossmodal_rerender`) matches the query again
against the map rendered at its pose, and ``task.storey_alias`` (:class:`StoreyAliasConfig`,
:mod:`diffloc.pipeline.crossmodal_alias`) against the map rendered at the same pose on the
other floors. Each lists the ``map`` options it runs on (none by default; the scene's
``task/scene/crossmodal_<scene>.yaml`` turns them on where they were chosen).

Example:
    >>> RerenderConfig(maps=["mesh"]).maps, StoreyAliasConfig().maps
    (['mesh'], [])
    >>> RerenderConfig(maps=["images"])
    Traceback (most recent call last):
    ...
    ValueError: task.rerender.maps: 'images' is not one of the maps it can check (...)
"""

from __future__ import annotations

from dataclasses import dataclass, field

from diffloc.checks import check_number

__all__ = ["ALIAS_MAPS", "RERENDER_MAPS", "RerenderConfig", "StoreyAliasConfig"]

RERENDER_MAPS = ("tls", "cloud", "mesh", "nerf")
"""The ``map`` options the re-render check can render at a pose found."""

ALIAS_MAPS = ("tls", "cloud", "mesh")
"""The ``map`` options whose accepted poses the storey-alias test can check (rendered at any
pose in tens of milliseconds)."""


def _check_maps(maps: list[str], allowed: tuple[str, ...], setting: str) -> None:
    """Refuse a ``map`` option of ``maps`` not in ``allowed`` (the message names them)."""
    for option in maps:
        if option not in allowed:
            raise ValueError(
                f"{setting}: {option!r} is not one of the maps it can check ({', '.join(allowed)})"
            )


@dataclass
class RerenderConfig:
    """``task.rerender``: a second look at each refused pose, on a render made at that pose.

    The localiser matches a query against database renders up to the render spacing and 45 deg
    from it, so a right pose can rest on few inliers over part of the image and be refused.
    With the check, the map is rendered at each refused pose, the query matched against that
    render, PnP solved again, and the new pose validated by the localiser's own tests (the
    rival test stays the localisation's verdict); the new pose and verdict replace the first
    (:mod:`diffloc.pipeline.crossmodal_rerender`). Accepted poses are kept as they are.

    Attributes:
        maps: the ``map`` options checked (any of :data:`RERENDER_MAPS`; empty, the default:
            off; ``task/scene/crossmodal_indoor.yaml`` turns it on where it was chosen).
    """

    maps: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        _check_maps(self.maps, RERENDER_MAPS, "task.rerender.maps")


@dataclass
class StoreyAliasConfig:
    """``task.storey_alias``: refuse an accepted pose that another floor explains at least as
    well (:mod:`diffloc.pipeline.crossmodal_alias`, :mod:`diffloc.reloc.storey_alias`).

    The map is rendered at the pose and at the same pose on each other floor of its render
    poses; the query is matched against each render and PnP solved. The pose is refused when
    a render on another floor gives a pose at least the validation's ``theta_dist_m`` away
    with at least ``ratio`` times the inliers of the render at the pose.

    Attributes:
        maps: the ``map`` options tested (any of :data:`ALIAS_MAPS`; empty, the default: off;
            ``task/scene/crossmodal_indoor.yaml`` turns it on for ``tls``).
        ratio: 1.0: the other floor explains the query at least as well. Chosen on indoor
            seed 0 (``experiments/storey_alias_check.py``): the TLS cloud's one wrong accepted
            pose (2.98 m, one storey, off) gave 445 inliers on the other floor against 252 at
            the pose (1.77); right mesh poses where the storeys look alike reached 0.70-0.84,
            so the validation's own rival ratio 0.7 would refuse three of them.

    Example:
        >>> StoreyAliasConfig().maps, StoreyAliasConfig(maps=["tls"]).ratio
        ([], 1.0)
    """

    maps: list[str] = field(default_factory=list)
    ratio: float = 1.0

    def __post_init__(self) -> None:
        _check_maps(self.maps, ALIAS_MAPS, "task.storey_alias.maps")
        check_number(self.ratio, "task.storey_alias.ratio", 0.0, open_low=True)
