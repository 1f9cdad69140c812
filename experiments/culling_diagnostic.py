"""Why keyframe culling does or does not fire: tracks observed vs points geometrically visible.

Usage:
    python experiments/culling_diagnostic.py <dataset> <database folder> [--record <json>]

Seed 1's rule removes a keyframe when ``redundant_fraction`` (90 %) of its map points are
observed by ``min_other_observers`` (3) other keyframes. Whether that can happen depends on how
long the builder's tracks are. This script reports, for a saved database:

- ``observations_per_point``: median and the fraction of points with more than
  ``min_other_observers`` observations (the builder's tracks);
- ``redundancy``: per ``min_other_observers`` in 1 .. the configured value, the largest
  redundancy of a keyframe and how many keyframes reach ``redundant_fraction``;
- ORACLE (reads the dataset's ground-truth depth; a diagnostic, never used by the pipeline):
  ``visible_keyframes_per_point`` (median number of keyframes in whose image the point projects
  onto its true surface, within ``--depth-tolerance`` metres), ``oracle_redundant_keyframes``
  (keyframes that would be redundant if every such visibility were an observation),
  ``observed_over_visible`` (observations / visibilities) and ``visible_with_keypoint_within_px``
  (visibilities with a detected keypoint within ``--keypoint-px`` of the projection: the
  detector's repeatability, an upper bound of what any matcher could observe).

The keyframe sources are ``keyframe_sources`` of ``update_db.json`` or, for a database as
built, the database sequence's ``keyframe_frames`` of ``build_db.json``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

import torch

from diffloc.database.culling import CullingConfig, redundancy
from diffloc.database.database import VisualDatabase
from diffloc.geometry.se3 import invert, transform_points
from diffloc.io.dataset import read_sequence

DEPTH_TOLERANCE_M = 0.1
"""A point is visible in a keyframe if it lies this close to the true depth at its pixel."""
KEYPOINT_PX = 2.0
"""A visibility is "repeatable" if a keypoint was detected this close to the projection."""


def visibility(
    dataset: Path,
    db: VisualDatabase,
    sources: Sequence[tuple[str, int]],
    depth_tolerance_m: float = DEPTH_TOLERANCE_M,
    keypoint_px: float = KEYPOINT_PX,
) -> tuple[torch.Tensor, torch.Tensor]:
    """ORACLE: which map points each keyframe sees on the true surface (ground-truth depth).

    Args:
        dataset: the dataset folder (with depth images).
        db: the database.
        sources: ``(sequence, frame)`` of every keyframe.
        depth_tolerance_m: largest |point depth - true depth| of a visible point.
        keypoint_px: radius of the repeatability test.

    Returns:
        ``(visible, repeatable)``: (K, P) bool visible points, and visible points with a
        keypoint of that keyframe within ``keypoint_px`` of the projection.
    """
    sequences: dict = {}
    visible, repeatable = [], []
    for k, (name, frame) in enumerate(sources):
        sequence = sequences.setdefault(name, read_sequence(dataset, name))
        camera = db.camera(k)
        uv, valid = camera.project_world(db.point_positions, db.T_wc[k])
        z = transform_points(invert(db.T_wc[k]), db.point_positions)[:, 2]
        depth = sequence.load_depth(frame).double().reshape(camera.height, camera.width)
        u = uv[:, 0].round().long().clamp(0, camera.width - 1)
        v = uv[:, 1].round().long().clamp(0, camera.height - 1)
        truth = depth[v, u]
        seen = valid & camera.in_image(uv) & (truth > 0) & ((z - truth).abs() < depth_tolerance_m)
        near = torch.zeros_like(seen)
        index = torch.nonzero(seen).flatten()
        keypoints = db.keypoints[db.keyframe_slice(k)].double()
        if len(index) and len(keypoints):
            near[index] = torch.cdist(uv[index], keypoints).min(1).values <= keypoint_px
        visible.append(seen)
        repeatable.append(near)
    return torch.stack(visible), torch.stack(repeatable)


def culling_diagnostic(
    dataset: Path,
    db: VisualDatabase,
    sources: Sequence[tuple[str, int]],
    culling: CullingConfig,
    depth_tolerance_m: float = DEPTH_TOLERANCE_M,
    keypoint_px: float = KEYPOINT_PX,
) -> dict:
    """The diagnostic of the module docstring for one database.

    Args:
        dataset: the dataset folder.
        db: the database.
        sources: ``(sequence, frame)`` of every keyframe.
        culling: the culling thresholds the database was built with.
        depth_tolerance_m: see :func:`visibility`.
        keypoint_px: see :func:`visibility`.

    Returns:
        A JSON-ready dict.
    """
    if len(sources) != db.num_keyframes:
        raise ValueError(f"{len(sources)} keyframe sources for {db.num_keyframes} keyframes")
    counts = db.observation_counts().double()
    result: dict = {
        "keyframes": db.num_keyframes,
        "map_points": db.num_points,
        "observations_per_point": {
            "median": float(counts.median()),
            "more_than_min_other_observers": float(
                (counts > culling.min_other_observers).double().mean()
            ),
        },
        "redundancy": {},
    }
    for observers in range(1, culling.min_other_observers + 1):
        config = CullingConfig(culling.redundant_fraction, observers, culling.new_point_window)
        score = redundancy(db, config)
        result["redundancy"][f"min_other_observers_{observers}"] = {
            "max": float(score.max()),
            "keyframes_at_threshold": int((score >= culling.redundant_fraction).sum()),
        }
    visible, repeatable = visibility(dataset, db, sources, depth_tolerance_m, keypoint_px)
    obs = db.observations()
    others = visible.sum(0)[obs[:, 2]] - visible[obs[:, 0], obs[:, 2]].long()
    well_seen = (others >= culling.min_other_observers).double()
    per_keyframe = torch.bincount(obs[:, 0], minlength=db.num_keyframes).double()
    fraction = torch.bincount(obs[:, 0], well_seen, minlength=db.num_keyframes)
    fraction = fraction / per_keyframe.clamp(min=1)
    result["oracle"] = {
        "depth_tolerance_m": depth_tolerance_m,
        "keypoint_px": keypoint_px,
        "visible_keyframes_per_point": float(visible.sum(0).double().median()),
        "oracle_redundant_keyframes": int((fraction >= culling.redundant_fraction).sum()),
        "observed_over_visible": float(len(obs) / max(int(visible.sum()), 1)),
        "visible_with_keypoint_within_px": float(repeatable.sum() / visible.sum().clamp(min=1)),
    }
    return result


def read_record(
    database: Path, record_path: Path | None = None
) -> tuple[list[tuple[str, int]], CullingConfig]:
    """Keyframe sources and culling thresholds from the stage record next to the database
    (``update_db.json``, else ``build_db.json``) or ``record_path``."""
    if record_path is None:
        candidates = (database.parent / "update_db.json", database.parent / "build_db.json")
        record_path = next((c for c in candidates if c.is_file()), None)
    if record_path is None:
        raise FileNotFoundError(f"no update_db.json or build_db.json next to {database}")
    record = json.loads(record_path.read_text())
    if "keyframe_sources" in record:
        db_config = record["config"]["db"]
        sources = [(str(name), int(frame)) for name, frame in record["keyframe_sources"]]
    else:
        db_config = record["config"]
        sources = [(db_config["sequence"], int(frame)) for frame in record["keyframe_frames"]]
    return sources, CullingConfig(**db_config["builder"]["culling"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("database", type=Path)
    parser.add_argument("--record", type=Path, default=None)
    parser.add_argument("--depth-tolerance", type=float, default=DEPTH_TOLERANCE_M)
    parser.add_argument("--keypoint-px", type=float, default=KEYPOINT_PX)
    args = parser.parse_args()
    db = VisualDatabase.load(args.database)
    sources, culling = read_record(args.database, args.record)
    result = culling_diagnostic(
        args.dataset, db, sources, culling, args.depth_tolerance, args.keypoint_px
    )
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
