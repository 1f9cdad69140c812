"""The storey-alias stage of ``diffloc task=crossmodal``: accepted poses tested on every floor.

``<dataset>/crossmodal/<map>/alias_<sequence>/`` (``alias.json``) holds ``alias.npz``: for
every accepted pose of the sequence's localisation, the inliers of the query against the map
rendered at the pose and at the same pose on each other floor, and whether it is a storey
alias (:mod:`diffloc.reloc.storey_alias`: an alias render's pose at least the validation's
``theta_dist_m`` away with at least ``task.storey_alias.ratio`` times the inliers of the render
at the pose). An alias is refused: the answers are the localisation's with those poses no
longer accepted (:meth:`SequenceAliases.apply`). Keyed on the localisation's outputs (and the
re-render check's, :mod:`diffloc.pipeline.crossmodal_rerender`, when it ran first), the map's,
the render poses' (their floors) and the localiser's settings; query ground truth is never
read.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from diffloc.crossmodal.database import RenderedDatabase
from diffloc.crossmodal.synthesize import RGBDMap
from diffloc.io.atomic import atomic_open
from diffloc.io.dataset import read_sequence
from diffloc.io.npz import read_npz_archive, read_npz_fields, write_npz
from diffloc.pipeline.crossmodal_pose_checks import ALIAS_MAPS
from diffloc.pipeline.crossmodal_stage import (
    SequenceLocalization,
    crossmodal_folder,
    scaled_images,
    sequence_inputs,
    stage_command,
)
from diffloc.pipeline.stage import LockLevel, StageOutcome, StageSummary, open_stage, stage_key
from diffloc.progress import progress
from diffloc.reloc.rendered import RenderedLocalizerConfig, localizer_networks
from diffloc.reloc.storey_alias import (
    AliasEvidence,
    floor_heights,
    is_storey_alias,
    storey_alias_evidence,
)

__all__ = ["AliasSummary", "SequenceAliases", "storey_alias_stage"]


@dataclass(frozen=True)
class AliasSummary(StageSummary):
    """The ``alias`` summary: of ``queries`` frames of ``sequence``, ``checked`` accepted poses
    were tested on ``floors`` floors and ``aliases`` refused; the median process CPU ms per
    checked pose and the load average it ran under."""

    sequence: str
    queries: int
    floors: int
    checked: int
    aliases: int
    median_cpu_ms: float | None
    load_average: list[float]


@dataclass(frozen=True)
class SequenceAliases:
    """The storey-alias test of the C accepted poses of a sequence with F floors.

    Attributes:
        query: (C,) int64 index into the localisation's queries.
        own_inliers: (C,) int64 inliers against the render at the pose (0: no pose; -1: not
            rendered, the map has one floor).
        alias_inliers: (C, F - 1) int64 inliers against each alias render (0: no pose).
        alias_distance_m: (C, F - 1) float64 distance of each alias render's pose from the
            accepted pose (NaN: no pose).
        alias: (C,) bool, a storey alias (refused).
        cpu_ms: (C,) float64 process CPU ms of each test.
    """

    query: np.ndarray
    own_inliers: np.ndarray
    alias_inliers: np.ndarray
    alias_distance_m: np.ndarray
    alias: np.ndarray
    cpu_ms: np.ndarray

    @classmethod
    def load(cls, path: Path) -> SequenceAliases:
        """Read ``alias.npz``.

        Raises:
            ValueError: an archive without some of the arrays (the message names the file).
        """
        return cls(
            **read_npz_fields(path, [f.name for f in fields(cls)], "run the alias test again")
        )

    def apply(self, loc: SequenceLocalization) -> SequenceLocalization:
        """The localisation with the storey aliases no longer accepted."""
        accepted = loc.accepted.astype(bool).copy()
        accepted[self.query[self.alias]] = False
        return replace(loc, accepted=accepted)


def _test_all(
    rgbd_map: RGBDMap,
    db: RenderedDatabase,
    loc: SequenceLocalization,
    heights: torch.Tensor,
    dataset: Path,
    sequence: str,
    config: RenderedLocalizerConfig,
    ratio: float,
    show_progress: bool,
) -> dict[str, np.ndarray]:
    """The arrays of :class:`SequenceAliases` for the accepted poses of ``loc``."""
    seq = read_sequence(dataset, sequence)
    camera = seq.camera.scaled(db.camera.width / seq.camera.width)
    networks = localizer_networks(config)
    min_distance_m = config.validation.theta_dist_m
    queries = np.flatnonzero(loc.accepted).astype(np.int64)
    evidence: list[AliasEvidence] = []
    cpu_ms = []
    with torch.no_grad():
        for q in progress(queries.tolist(), f"alias {sequence}", show_progress):
            start = time.process_time()
            image = scaled_images(seq, camera, [int(loc.frames[q])])[0]
            view = (image, networks[0].extract(image), camera)
            T_wc = torch.from_numpy(loc.T_wc[q])
            evidence.append(
                storey_alias_evidence(rgbd_map, T_wc, heights, db.camera, view, networks, config)
            )
            cpu_ms.append(1000.0 * (time.process_time() - start))
    others = max(len(heights) - 1, 0)
    return {
        "query": queries,
        "own_inliers": np.array([e.own_inliers for e in evidence], dtype=np.int64),
        "alias_inliers": np.array([e.alias_inliers for e in evidence], dtype=np.int64).reshape(
            len(evidence), others
        ),
        "alias_distance_m": np.array(
            [e.alias_distance_m for e in evidence], dtype=np.float64
        ).reshape(len(evidence), others),
        "alias": np.array(
            [is_storey_alias(e, min_distance_m, ratio) for e in evidence],
            dtype=bool,
        ),
        "cpu_ms": np.array(cpu_ms, dtype=np.float64),
    }


def storey_alias_stage(
    dataset: Path,
    option: str,
    sequence: str,
    localization: tuple[SequenceLocalization, StageOutcome],
    rendered: tuple[RGBDMap, StageOutcome, RenderedDatabase],
    render_poses: tuple[str, StageOutcome],
    config: RenderedLocalizerConfig,
    ratio: float,
    show_progress: bool = False,
) -> tuple[SequenceAliases, StageOutcome[AliasSummary]]:
    """Test the accepted poses of ``sequence`` for storey aliases (made or reused).

    Args:
        dataset: the dataset folder.
        option: the ``map`` option (one of :data:`ALIAS_MAPS`).
        sequence: the query sequence.
        localization: its localisation and that stage's outcome.
        rendered: the map's renderer, the map stage's outcome and the database (its camera).
        render_poses: the point map the render poses were chosen on (``"tls_map"`` or
            ``"lidar_map"``) and that stage's outcome (``poses.npz``: the floors).
        config: the localiser's settings (matching, PnP; its validation's ``theta_dist_m``).
        ratio: ``task.storey_alias.ratio``.
        show_progress: a progress bar over the accepted poses.

    Raises:
        ValueError: ``option`` is not one of
            :data:`~diffloc.pipeline.crossmodal_pose_checks.ALIAS_MAPS`, or the localiser has no
            validation (its accepted poses are not validated).
    """
    if option not in ALIAS_MAPS:
        raise ValueError(f"the storey-alias test runs on map={'|'.join(ALIAS_MAPS)}, not {option}")
    if config.validation is None:
        raise ValueError("the storey-alias test needs the localiser's validation (theta_dist_m)")
    loc, loc_outcome = localization
    rgbd_map, map_outcome, db = rendered
    point_map, poses_outcome = render_poses
    poses_path = crossmodal_folder(dataset) / f"poses_{point_map}" / "poses.npz"
    folder = crossmodal_folder(dataset) / option / f"alias_{sequence}"
    key = stage_key(
        {"localizer": asdict(config), "ratio": ratio},
        {
            "localization": loc_outcome.outputs,
            "map": map_outcome.outputs,
            "render_poses": poses_outcome.outputs["poses.npz"],
            **sequence_inputs(dataset, sequence, with_poses=False),
        },
    )
    with open_stage(folder, "alias", stage_command(dataset, option), LockLevel.UPDATED) as stage:
        summary = stage.reusable(key, AliasSummary)
        if summary is None:
            arrays = read_npz_archive(poses_path)
            heights = floor_heights(
                torch.from_numpy(arrays["T_wc"]), torch.from_numpy(arrays["floor_index"])
            )
            tested = _test_all(
                rgbd_map, db, loc, heights, dataset, sequence, config, ratio, show_progress
            )
            with atomic_open(stage.workdir() / "alias.npz", "wb") as handle:
                write_npz(handle, tested)
            summary = AliasSummary(
                sequence=sequence,
                queries=len(loc.frames),
                floors=len(heights),
                checked=len(tested["query"]),
                aliases=int(tested["alias"].sum()),
                median_cpu_ms=float(np.median(tested["cpu_ms"])) if len(tested["query"]) else None,
                load_average=list(os.getloadavg()),
            )
            summary = stage.commit(key, summary, ["alias.npz"])
        outcome = stage.outcome(summary)
        return SequenceAliases.load(folder / "alias.npz"), outcome
