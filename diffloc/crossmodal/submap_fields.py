"""Radiance-field submaps as one RGB-D map: each pose rendered by the submap that serves it.

Seed 2 (III-D3) trains one radiance field per submap of the mapping trajectory and renders its
database from them. Here a pose is served by the submap whose core frames have the largest
affinity (position and viewing direction) to it
(:func:`~diffloc.maps.nerf.submaps.serving_submap`), and rendered by that submap's field
(:class:`~diffloc.crossmodal.nerf_map.RadianceFieldMap`: mean appearance code, pixels of low
opacity are holes).

A folder holds such a map (:func:`write_submap_fields`, :meth:`SubmapFieldMap.from_folder`):

- ``submaps.json``: the clustering (:func:`~diffloc.maps.nerf.submaps.save_submaps`);
- ``mapping_poses.npz``: ``T_wc`` (N, 4, 4) of the mapping frames the submaps index;
- ``render.json``: ``format_version``, ``min_opacity`` and the ``fields`` present;
- ``submap_<k>/``: the exported field of submap k
  (:func:`~diffloc.maps.nerf.export.export_field`), for the submaps that serve some pose.

A pose served by a submap whose field is absent is a clear error, never a render of another
submap.

Usage (``tests/test_crossmodal_nerf.py`` runs it on the tiny scene)::

    write_submap_fields(folder, submaps, config, mapping.T_wc, {0: files_0, 1: files_1}, 0.5)
    views = SubmapFieldMap.from_folder(folder).render(T_wc, camera)
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from diffloc.checks import ShapeError, check_shape
from diffloc.crossmodal.nerf_map import RadianceFieldMap
from diffloc.crossmodal.synthesize import RGBD
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.atomic import atomic_open, atomic_write_bytes, atomic_write_text
from diffloc.io.json_record import read_json_record
from diffloc.io.npz import read_npz_archive, write_npz
from diffloc.maps.nerf.submaps import (
    Submap,
    SubmapConfig,
    load_submaps,
    save_submaps,
    serving_submap,
)

__all__ = ["SubmapFieldMap", "write_submap_fields"]

FORMAT_VERSION = 1
_RENDER, _POSES, _SUBMAPS = "render.json", "mapping_poses.npz", "submaps.json"


def write_submap_fields(
    folder: str | os.PathLike,
    submaps: list[Submap],
    config: SubmapConfig,
    mapping_T_wc: torch.Tensor,
    fields: dict[int, dict[str, bytes]],
    min_opacity: float,
) -> None:
    """Write a submap-field map into ``folder`` (module docstring; the caller makes it atomic,
    e.g. a stage's work folder).

    Args:
        folder: the folder (created).
        submaps: the clustering of the mapping trajectory.
        config: its settings (the affinity scales that pick the serving submap).
        mapping_T_wc: (N, 4, 4) the mapping poses the submaps index.
        fields: submap index -> file name -> content of its exported field folder.
        min_opacity: pixels of lower opacity are holes.

    Raises:
        ValueError: a field of a submap the clustering does not have.
    """
    check_shape(mapping_T_wc, "N,4,4", "mapping_T_wc")
    unknown = sorted(set(fields) - {s.index for s in submaps})
    if unknown:
        raise ValueError(f"fields of submaps {unknown}, which the clustering does not have")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    save_submaps(folder / _SUBMAPS, submaps, config)
    with atomic_open(folder / _POSES, "wb") as handle:
        write_npz(handle, {"T_wc": mapping_T_wc.double().numpy()})
    for k, files in sorted(fields.items()):
        for name, content in files.items():
            atomic_write_bytes(folder / f"submap_{k}" / name, content)
    record = {
        "format_version": FORMAT_VERSION,
        "min_opacity": min_opacity,
        "fields": sorted(fields),
    }
    atomic_write_text(folder / _RENDER, json.dumps(record, indent=1) + "\n")


@dataclass(frozen=True, eq=False)
class SubmapFieldMap:
    """Radiance-field submaps rendered into RGB-D images, each pose by its serving submap.

    Attributes:
        fields: submap index -> its field as an RGB-D map.
        submaps: the clustering of the mapping trajectory.
        config: its settings.
        mapping_T_wc: (N, 4, 4) float64 mapping poses the submaps index.

    Raises:
        ValueError: no field, or a field of a submap the clustering does not have.
    """

    fields: dict[int, RadianceFieldMap]
    submaps: list[Submap]
    config: SubmapConfig
    mapping_T_wc: torch.Tensor

    def __post_init__(self) -> None:
        check_shape(self.mapping_T_wc, "N,4,4", "mapping_T_wc")
        if not self.fields:
            raise ValueError("a submap-field map needs at least one field")
        unknown = sorted(set(self.fields) - {s.index for s in self.submaps})
        if unknown:
            raise ValueError(f"fields of submaps {unknown}, which the clustering does not have")

    @classmethod
    def from_folder(cls, folder: str | os.PathLike) -> SubmapFieldMap:
        """Read :func:`write_submap_fields` output.

        Raises:
            FileNotFoundError: a file of the map is missing.
            ValueError: a foreign or corrupt file (the message names it).
        """
        folder = Path(folder)
        for name in (_RENDER, _POSES):
            if not (folder / name).is_file():
                raise FileNotFoundError(f"{folder / name} does not exist: not a submap-field map")
        record = read_json_record(folder / _RENDER)
        if record.get("format_version") != FORMAT_VERSION:
            raise ValueError(f"{folder / _RENDER}: not a format {FORMAT_VERSION} submap-field map")
        submaps, config = load_submaps(folder / _SUBMAPS)
        poses = read_npz_archive(folder / _POSES)
        if "T_wc" not in poses:
            raise ValueError(f"{folder / _POSES} has no T_wc array")
        fields = {
            int(k): RadianceFieldMap.from_folder(folder / f"submap_{k}", record["min_opacity"])
            for k in record["fields"]
        }
        return cls(fields, submaps, config, torch.from_numpy(poses["T_wc"]))

    def serving(self, T_wc: torch.Tensor) -> torch.Tensor:
        """(B,) int64 index of the submap that serves each pose of ``T_wc`` (B, 4, 4)."""
        return serving_submap(T_wc, self.submaps, self.mapping_T_wc, self.config)

    def render(self, T_wc: torch.Tensor, camera: PinholeCamera) -> RGBD:
        """RGB-D images (B, 3, H, W) and (B, 1, H, W) seen from ``T_wc`` (B, 4, 4).

        Raises:
            ShapeError: ``T_wc`` not (B, 4, 4) or empty.
            ValueError: a pose served by a submap whose field is absent.
        """
        check_shape(T_wc, "B,4,4", "T_wc")
        if T_wc.shape[0] == 0:
            raise ShapeError("T_wc must hold at least one pose, got shape (0, 4, 4)")
        serving = self.serving(T_wc)
        missing = sorted(set(serving.tolist()) - set(self.fields))
        if missing:
            raise ValueError(
                f"poses served by submaps {missing}, whose fields this map lacks "
                f"(it has {sorted(self.fields)})"
            )
        rgb = torch.zeros(len(T_wc), 3, camera.height, camera.width)
        depth = torch.zeros(len(T_wc), 1, camera.height, camera.width)
        for k in np.unique(serving.numpy()).tolist():
            index = torch.nonzero(serving == k)[:, 0]
            part = self.fields[k].render(T_wc[index], camera)
            rgb[index], depth[index] = part.rgb, part.depth
        return RGBD(rgb, depth)
