"""The re-render stage of ``diffloc task=crossmodal``: a second look at each refused pose, on a
render made at it.

``<dataset>/crossmodal/<map>/rerender_<sequence>/`` (``rerender.json``) holds
``rerender.npz``: for every query of the sequence's localisation with a pose found that the
validation refused, the map rendered at that pose with the database camera, the query matched
against the render (the localiser's XFeat and LighterGlue), lifted by the render's depth and
PnP solved again (:func:`~diffloc.reloc.rerender.rerender_candidate`), and the new pose's
evidence (inliers, coverage, plane share, the photometric consistency of the render warped
into the query) validated by the localiser's own tests
(:func:`~diffloc.pipeline.crossmodal_replay.replay_validation`) but one: the rival test stays
the localisation's verdict. There every candidate was matched alike, against database renders
up to the render spacing away; a pose matched against a render at its own viewpoint out-counts
rivals matched that way, so on the re-render's evidence the rival test lets wrong poses
through (indoor seeds 0-2, ``experiments/rerender_check.py``: mesh seed 2 and the TLS cloud
each gained wrong poses a rival had refused, most of them one storey off). Accepted poses are
not looked at again: on indoor seeds 0-2 (mesh, lidar and TLS clouds) re-rendering them too
refused no wrong pose and up to 2 right ones per map and seed, at a render and a match per
query. The answers are the localisation's with the refused poses' new poses and verdicts
(:meth:`SequenceRerender.apply`); a query whose re-render gives no pose stays refused. Keyed
on the localisation's output, the map's and the localiser's settings; query ground truth is
never read.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from diffloc.crossmodal.database import RenderedDatabase
from diffloc.crossmodal.synthesize import RGBDMap
from diffloc.io.atomic import atomic_open
from diffloc.io.dataset import read_sequence
from diffloc.io.npz import read_npz_fields, write_npz
from diffloc.pipeline.crossmodal_pose_checks import RERENDER_MAPS
from diffloc.pipeline.crossmodal_replay import (
    REPLAYED_TESTS,
    recorded_evidence,
    replay_validation,
)
from diffloc.pipeline.crossmodal_stage import (
    SequenceLocalization,
    crossmodal_folder,
    scaled_images,
    sequence_inputs,
    stage_command,
)
from diffloc.pipeline.stage import LockLevel, StageOutcome, StageSummary, open_stage, stage_key
from diffloc.progress import progress
from diffloc.reloc.rendered import RenderedLocalizerConfig, localizer_networks, pose_evidence
from diffloc.reloc.rerender import rerender_candidate

__all__ = ["RerenderSummary", "SequenceRerender", "rerender_stage"]


@dataclass(frozen=True)
class RerenderSummary(StageSummary):
    """The ``rerender`` summary: of ``queries`` frames of ``sequence``, ``checked`` refused
    poses were re-rendered and ``accepted`` of them accepted on the re-render;
    ``median_moved_m``: median distance those moved; the median wall and process CPU ms per
    check and the load average it ran under."""

    sequence: str
    queries: int
    checked: int
    accepted: int
    median_moved_m: float | None
    median_wall_ms: float | None
    median_cpu_ms: float | None
    load_average: list[float]


@dataclass(frozen=True)
class SequenceRerender:
    """The re-render check of the P refused poses of a sequence.

    Attributes:
        query: (P,) int64 index into the localisation's queries.
        success: (P,) bool, PnP on the re-render found a pose.
        T_wc: (P, 4, 4) float64 that pose, camera-to-world (identity: none).
        num_matches: (P,) int64 LighterGlue matches with the re-render.
        num_points: (P,) int64 of those, matches with depth.
        num_inliers: (P,) int64 PnP inliers.
        coverage: (P,) float64 share of the query grid cells holding an inlier.
        plane_share: (P,) float64 share of the inliers on their dominant plane (NaN: no pose).
        photometric: (P,) float64 photometric consistency of the new pose (NaN: no pose or
            too little overlap).
        failed: (P, T) bool, the new pose fails each test of
            :data:`~diffloc.pipeline.crossmodal_replay.REPLAYED_TESTS`.
        accepted: (P,) bool, a pose was found and passes every test.
        wall_ms: (P,) float64 wall ms of each check (render, features, matching, PnP,
            photometric consistency).
        cpu_ms: (P,) float64 process CPU ms of each check.
    """

    query: np.ndarray
    success: np.ndarray
    T_wc: np.ndarray
    num_matches: np.ndarray
    num_points: np.ndarray
    num_inliers: np.ndarray
    coverage: np.ndarray
    plane_share: np.ndarray
    photometric: np.ndarray
    failed: np.ndarray
    accepted: np.ndarray
    wall_ms: np.ndarray
    cpu_ms: np.ndarray

    @classmethod
    def load(cls, path: Path) -> SequenceRerender:
        """Read ``rerender.npz``.

        Raises:
            ValueError: an archive without some of the arrays (the message names the file).
        """
        names = [f.name for f in fields(cls)]
        return cls(**read_npz_fields(path, names, "run the re-render check again"))

    def apply(self, loc: SequenceLocalization) -> SequenceLocalization:
        """The localisation with the re-render's poses, evidence and verdicts.

        Each checked (refused) query is accepted by its re-render's verdict (queries not
        checked keep the localisation's); where the re-render found a
        pose it replaces the pose, matches, points, inliers and photometric consistency (the
        ``candidate_*`` records stay the first pass's); the check's wall and CPU time is added
        to the query's.
        """
        q, found = self.query, self.query[self.success]
        arrays = {
            name: getattr(loc, name).copy()
            for name in ("T_wc", "num_matches", "num_points", "num_inliers", "photometric")
        }
        for name, values in arrays.items():
            values[found] = getattr(self, name)[self.success]
        accepted = loc.accepted.astype(bool).copy()
        accepted[q] = self.accepted
        without_photometric = loc.accepted_without_photometric.astype(bool).copy()
        others = [i for i, test in enumerate(REPLAYED_TESTS) if test != "photometric"]
        without_photometric[q] = self.success & ~self.failed[:, others].any(axis=1)
        time_ms, cpu_ms = loc.time_ms.copy(), loc.cpu_ms.copy()
        time_ms[q] += self.wall_ms
        cpu_ms[q] += self.cpu_ms
        return replace(
            loc,
            **arrays,
            accepted=accepted,
            accepted_without_photometric=without_photometric,
            time_ms=time_ms,
            cpu_ms=cpu_ms,
        )


def _check_all(
    rgbd_map: RGBDMap,
    db: RenderedDatabase,
    loc: SequenceLocalization,
    dataset: Path,
    sequence: str,
    config: RenderedLocalizerConfig,
    show_progress: bool,
) -> dict[str, np.ndarray]:
    """The arrays of :class:`SequenceRerender` for the refused poses of ``loc``."""
    seq = read_sequence(dataset, sequence)
    camera = seq.camera.scaled(db.camera.width / seq.camera.width)
    networks = localizer_networks(config)
    real = db.real.numpy()
    queries = np.flatnonzero(loc.success & ~loc.accepted.astype(bool)).astype(np.int64)
    # the rival test stays the localisation's: there every candidate was matched alike
    _, failed_before = replay_validation(
        recorded_evidence(loc), config.validation, real, config.min_photometric_real
    )
    without_rivals = replace(config.validation, ambiguity_ratio=None)
    rows = []
    with torch.no_grad():
        for q in progress(queries.tolist(), f"re-render {sequence}", show_progress):
            image = scaled_images(seq, camera, [int(loc.frames[q])])[0]
            generator = torch.Generator().manual_seed(config.seed)
            result = rerender_candidate(
                rgbd_map,
                torch.from_numpy(loc.T_wc[q]),
                db.camera,
                image,
                networks[0].extract(image),
                camera,
                networks,
                config,
                generator,
            )
            cand = result.candidate
            failed: tuple[str, ...] = ()
            if cand.success:
                _, tried = loc.candidates(q)
                evidence = pose_evidence(cand, (*tried, cand), result.photometric)
                _, verdicts = replay_validation(
                    [(int(loc.reference[q]), evidence)],
                    without_rivals,
                    real,
                    config.min_photometric_real,
                )
                failed = (*verdicts[0], *(t for t in failed_before[q] if t == "rival"))
            rows.append(
                {
                    "success": cand.success,
                    "T_wc": cand.T_wc.numpy() if cand.success else np.eye(4),
                    "num_matches": cand.num_matches,
                    "num_points": cand.num_points,
                    "num_inliers": cand.num_inliers,
                    "coverage": cand.coverage,
                    "plane_share": cand.plane_share,
                    "photometric": result.photometric,
                    "failed": [test in failed for test in REPLAYED_TESTS],
                    "accepted": cand.success and not failed,
                    "wall_ms": sum(result.wall_ms.values()),
                    "cpu_ms": sum(result.cpu_ms.values()),
                }
            )
    return {"query": queries, **{name: _stacked(rows, name) for name in _ROW_FIELDS}}


_ROW_FIELDS = tuple(f.name for f in fields(SequenceRerender))[1:]
_INTEGERS = ("num_matches", "num_points", "num_inliers")
_FLAGS = ("success", "failed", "accepted")


def _stacked(rows: list[dict], name: str) -> np.ndarray:
    """The ``name`` values of the checks' rows as one array (its shape also with no row)."""
    dtype = bool if name in _FLAGS else np.int64 if name in _INTEGERS else np.float64
    tail = {"T_wc": (4, 4), "failed": (len(REPLAYED_TESTS),)}.get(name, ())
    return np.array([row[name] for row in rows], dtype=dtype).reshape(len(rows), *tail)


def rerender_stage(
    dataset: Path,
    option: str,
    sequence: str,
    localization: tuple[SequenceLocalization, StageOutcome],
    rendered: tuple[RGBDMap, StageOutcome, RenderedDatabase],
    config: RenderedLocalizerConfig,
    show_progress: bool = False,
) -> tuple[SequenceRerender, StageOutcome[RerenderSummary]]:
    """Look again at the refused poses of ``sequence`` on renders at them (made or reused).

    Args:
        dataset: the dataset folder.
        option: the ``map`` option (one of
            :data:`~diffloc.pipeline.crossmodal_pose_checks.RERENDER_MAPS`).
        sequence: the query sequence.
        localization: its localisation and that stage's outcome.
        rendered: the map's renderer, the map stage's outcome and the database (its camera).
        config: the localiser's settings (matching, PnP, validation).
        show_progress: a progress bar over the refused poses.

    Raises:
        ValueError: ``option`` is not one of
            :data:`~diffloc.pipeline.crossmodal_pose_checks.RERENDER_MAPS`, or the localiser
            has no validation (nothing to validate the new pose with).
    """
    if option not in RERENDER_MAPS:
        raise ValueError(f"the re-render check runs on map={'|'.join(RERENDER_MAPS)}, not {option}")
    if config.validation is None:
        raise ValueError("the re-render check validates with the localiser's validation: set one")
    loc, loc_outcome = localization
    rgbd_map, map_outcome, db = rendered
    folder = crossmodal_folder(dataset) / option / f"rerender_{sequence}"
    key = stage_key(
        {"localizer": asdict(config), "poses": "refused"},
        {
            "localization": loc_outcome.outputs,
            "map": map_outcome.outputs,
            **sequence_inputs(dataset, sequence, with_poses=False),
        },
    )
    command = stage_command(dataset, option)
    with open_stage(folder, "rerender", command, LockLevel.UPDATED) as stage:
        summary = stage.reusable(key, RerenderSummary)
        if summary is None:
            checked = _check_all(rgbd_map, db, loc, dataset, sequence, config, show_progress)
            with atomic_open(stage.workdir() / "rerender.npz", "wb") as handle:
                write_npz(handle, checked)
            summary = _summary(sequence, loc, checked)
            summary = stage.commit(key, summary, ["rerender.npz"])
        outcome = stage.outcome(summary)
        return SequenceRerender.load(folder / "rerender.npz"), outcome


def _summary(
    sequence: str, loc: SequenceLocalization, checked: dict[str, np.ndarray]
) -> RerenderSummary:
    """The stage summary of the arrays of :func:`_check_all`."""
    query, accepted = checked["query"], checked["accepted"]
    moved = np.linalg.norm(
        checked["T_wc"][accepted, :3, 3] - loc.T_wc[query[accepted], :3, 3], axis=1
    )

    def median(values: np.ndarray) -> float | None:
        return round(float(np.median(values)), 3) if len(values) else None

    return RerenderSummary(
        sequence=sequence,
        queries=len(loc.frames),
        checked=len(query),
        accepted=int(accepted.sum()),
        median_moved_m=median(moved),
        median_wall_ms=median(checked["wall_ms"]),
        median_cpu_ms=median(checked["cpu_ms"]),
        load_average=list(os.getloadavg()),
    )
