"""The refinement stage of ``diffloc task=crossmodal`` (``task.refine.enabled=true``).

After a sequence's localisation, every accepted pose is refined by render-and-compare against
the map the database was rendered from (:func:`~diffloc.optim.render_refine.refine_query`):
``map=nerf`` through the radiance-field submaps of the map stage (``fields/``; each query
served by the submap of its localised pose, its appearance code fitted there), ``map=tls`` /
``map=cloud`` through the coloured cloud of the map stage (``colored_map.ply``, thinned and
soft-splatted). Other maps are refused before any work (:func:`check_refinable`): a textured
mesh or the mapping images have no differentiable render here.

``<dataset>/crossmodal/<map>/refine_<sequence>/`` (``refine.json``) holds
``refinement.npz`` (:class:`SequenceRefinement`); keyed on ``task.refine`` (but ``enabled``),
the localisation stage's output, the map stage's output and the query sequence's images and
calibration, so a changed refinement setting runs only the refinement again, and a changed
localisation runs it too. The query sequences' true poses are never read here.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

from diffloc.crossmodal.submap_fields import SubmapFieldMap
from diffloc.features.local import XFeatConfig, XFeatExtractor
from diffloc.io.atomic import atomic_open
from diffloc.io.dataset import read_sequence
from diffloc.io.npz import read_npz_fields, write_npz
from diffloc.maps.pointcloud import PointMap
from diffloc.optim.render_refine import NO_MAP, CloudMaps, FieldSubmaps, QueryMaps, refine_query
from diffloc.pipeline.crossmodal_config import REFINE_MAPS, CrossmodalRefineConfig
from diffloc.pipeline.crossmodal_stage import (
    SequenceLocalization,
    crossmodal_folder,
    sequence_inputs,
)
from diffloc.pipeline.hints import Command
from diffloc.pipeline.stage import LockLevel, StageOutcome, StageSummary, open_stage, stage_key
from diffloc.progress import progress

__all__ = [
    "REFINEMENT_RECORD",
    "MapSource",
    "RefineSummary",
    "SequenceRefinement",
    "check_refinable",
    "cloud_source",
    "field_source",
    "refine_sequence",
]

REFINEMENT_RECORD = 1
"""Version of ``refinement.npz``'s contents, part of the stage's key."""


def check_refinable(option: str) -> None:
    """Refuse ``task.refine.enabled`` with a map the refinement cannot render.

    Raises:
        ValueError: ``option`` is not one of :data:`REFINE_MAPS`; the message names them.

    Example:
        >>> check_refinable("nerf")
        >>> check_refinable("mesh")
        Traceback (most recent call last):
        ...
        ValueError: task.refine supports map=nerf|tls|cloud, not map=mesh (...)
    """
    if option not in REFINE_MAPS:
        raise ValueError(
            f"task.refine supports map={'|'.join(REFINE_MAPS)}, not map={option} (it refines "
            "through a differentiable render of the map; set task.refine.enabled=false)"
        )


@dataclass(frozen=True)
class MapSource:
    """The map a refinement renders: how to load it, and the identity of the output it is
    loaded from (part of the stage's key).

    Attributes:
        load: builds the map (called only when the stage computes).
        identity: the map stage's recorded identity of that output.
    """

    load: Callable[[], QueryMaps]
    identity: dict


def field_source(folder: Path, identity: dict, config: CrossmodalRefineConfig) -> MapSource:
    """``map=nerf``: the submap fields the map stage wrote to ``folder``
    (:class:`~diffloc.crossmodal.submap_fields.SubmapFieldMap`)."""

    def load() -> FieldSubmaps:
        fields_map = SubmapFieldMap.from_folder(folder)

        def field(k: int):
            return fields_map.fields[k].field, fields_map.fields[k].grid

        return FieldSubmaps(
            fields_map.submaps,
            fields_map.config,
            fields_map.mapping_T_wc,
            field,
            fields_map.fields,
            config.fit_steps,
        )

    return MapSource(load, identity)


def cloud_source(path: Path, identity: dict, config: CrossmodalRefineConfig) -> MapSource:
    """``map=tls|cloud``: the coloured cloud the map stage wrote to ``path``."""

    def load() -> CloudMaps:
        cloud = PointMap.load_ply(path)
        return CloudMaps(
            cloud.positions, cloud.colors, config.cloud_spacing_m, config.cloud_max_depth_m
        )

    return MapSource(load, identity)


@dataclass(frozen=True)
class RefineSummary(StageSummary):
    """The ``refine`` summary: of ``queries`` frames of ``sequence``, ``localised`` had an
    accepted pose and were refined, ``kept`` of those kept the refined pose; the median
    process CPU ms per refined query and the 1/5/15-minute load average it ran under."""

    sequence: str
    queries: int
    localised: int
    kept: int
    median_cpu_ms: float | None
    load_average: list[float]


@dataclass(frozen=True)
class SequenceRefinement:
    """The refinement of the R accepted poses of a sequence.

    Attributes:
        query: (R,) int64 index into the localisation's queries (its ``frames``).
        frames: (R,) int64 frame indices.
        T_wc_start: (R, 4, 4) float64 the localised poses.
        T_wc_refined: (R, 4, 4) float64 where the refinement ended (kept or not).
        T_wc: (R, 4, 4) float64 the answer: the refined pose where kept, else the start.
        kept: (R,) bool, the refined pose passed the acceptance rule (and the match check
            with ``task.refine.verify``).
        served: (R,) int64 the map part that served the query (a submap; 0 for a cloud; -1:
            none, the pose is kept as it was).
        cost_before: (R,) float64 mean robust cost per compared pixel at the start (NaN: not
            refined).
        cost_after: (R,) float64 the same at the refined pose.
        correlation: (R,) float64 colour correlation at the refined pose.
        checked: (R,) bool, the match check ran (only for a move that passed the rest).
        inliers_before: (R,) int64 aligned matches at the start (-1: not checked).
        inliers_after: (R,) int64 aligned matches at the refined pose (-1: not checked).
        cpu_ms: (R,) float64 process CPU ms per query (fit, check and refinement).
        wall_ms: (R,) float64 wall ms per query.
        fit_cpu_ms: (R,) float64 of it, the appearance fit's (0: a cloud).
        check_cpu_ms: (R,) float64 of it, the match check's (0: none).
    """

    query: np.ndarray
    frames: np.ndarray
    T_wc_start: np.ndarray
    T_wc_refined: np.ndarray
    T_wc: np.ndarray
    kept: np.ndarray
    served: np.ndarray
    cost_before: np.ndarray
    cost_after: np.ndarray
    correlation: np.ndarray
    checked: np.ndarray
    inliers_before: np.ndarray
    inliers_after: np.ndarray
    cpu_ms: np.ndarray
    wall_ms: np.ndarray
    fit_cpu_ms: np.ndarray
    check_cpu_ms: np.ndarray

    @classmethod
    def load(cls, path: Path) -> SequenceRefinement:
        """Read ``refinement.npz`` written by :func:`refine_sequence`.

        Raises:
            ValueError: an archive without some of the arrays, or whose arrays disagree in
                length or hold non-finite poses; the message names the file.
        """
        names = [f.name for f in fields(cls)]
        arrays = read_npz_fields(path, names, "run the refinement again")
        lengths = {len(arrays[name]) for name in names}
        if len(lengths) != 1:
            raise ValueError(f"{path}: arrays of different lengths {sorted(lengths)}")
        for name in ("T_wc_start", "T_wc"):
            if not np.isfinite(arrays[name]).all():
                raise ValueError(f"{path}: {name} holds non-finite poses")
        return cls(**{name: arrays[name] for name in names})

    def answers(self, loc: SequenceLocalization) -> np.ndarray:
        """(Q, 4, 4) the localisation's poses with the refined ones in place of the kept."""
        T_wc = loc.T_wc.copy()
        T_wc[self.query] = self.T_wc
        return T_wc


def _refine_all(
    maps: QueryMaps,
    loc: SequenceLocalization,
    dataset: Path,
    sequence: str,
    config: CrossmodalRefineConfig,
    show_progress: bool,
) -> dict[str, np.ndarray]:
    """The arrays of :class:`SequenceRefinement` for the accepted queries of ``loc``."""
    seq = read_sequence(dataset, sequence)
    query = np.flatnonzero(loc.accepted.astype(bool))
    T_start = torch.from_numpy(loc.T_wc[query]).double()
    served = maps.serving(T_start) if len(query) else []
    extractor = XFeatExtractor(XFeatConfig()) if config.verify else None
    check = config.check if config.verify else None
    settings = (seq.camera, config.image_scale, config.render, check, extractor)
    rows = []
    for i in progress(range(len(query)), f"refine {sequence}", show_progress):
        T0 = T_start[i][None]
        if served[i] == NO_MAP:
            rows.append(_unrefined(T0))
            continue
        image = seq.load_rgb(int(loc.frames[query[i]]))[None].double()
        done = refine_query(maps, served[i], image, T0, *settings)
        r, evidence = done.result, done.result.evidence
        rows.append(
            {
                "T_wc_refined": r.T_refined[0],
                "T_wc": r.T_wc[0],
                "kept": bool(r.accepted[0]),
                "cost_before": float(r.cost_before[0]),
                "cost_after": float(r.cost_after[0]),
                "correlation": float(r.correlation[0]),
                "checked": evidence is not None,
                "inliers_before": -1 if evidence is None else int(evidence.inliers_before[0]),
                "inliers_after": -1 if evidence is None else int(evidence.inliers_after[0]),
                "cpu_ms": done.cpu_ms,
                "wall_ms": done.wall_ms,
                "fit_cpu_ms": float(done.info.get("fit_cpu_ms", 0.0)),
                "check_cpu_ms": float(done.info.get("check_cpu_ms", 0.0)),
            }
        )

    def column(name: str, dtype) -> np.ndarray:
        return np.array([row[name] for row in rows], dtype=dtype)

    def poses(name: str) -> np.ndarray:
        stacked = [row[name].double().numpy() for row in rows]
        return np.stack(stacked) if stacked else np.zeros((0, 4, 4))

    return {
        "query": query.astype(np.int64),
        "frames": loc.frames[query].astype(np.int64),
        "T_wc_start": T_start.numpy().reshape(-1, 4, 4),
        "T_wc_refined": poses("T_wc_refined"),
        "T_wc": poses("T_wc"),
        "kept": column("kept", bool),
        "served": np.array(served, dtype=np.int64),
        **{name: column(name, np.float64) for name in ("cost_before", "cost_after")},
        "correlation": column("correlation", np.float64),
        "checked": column("checked", bool),
        "inliers_before": column("inliers_before", np.int64),
        "inliers_after": column("inliers_after", np.int64),
        **{name: column(name, np.float64) for name in TIMES},
    }


TIMES = ("cpu_ms", "wall_ms", "fit_cpu_ms", "check_cpu_ms")
"""The arrays of ``refinement.npz`` that hold times."""


def _unrefined(T0: torch.Tensor) -> dict:
    """The row of a query no part of the map serves: its pose kept, nothing measured."""
    nan = float("nan")
    return {
        "T_wc_refined": T0[0],
        "T_wc": T0[0],
        "kept": False,
        "cost_before": nan,
        "cost_after": nan,
        "correlation": nan,
        "checked": False,
        "inliers_before": -1,
        "inliers_after": -1,
        **{name: 0.0 for name in TIMES},
    }


def refine_sequence(
    dataset: Path,
    option: str,
    sequence: str,
    localization: tuple[SequenceLocalization, StageOutcome],
    source: MapSource,
    config: CrossmodalRefineConfig,
    show_progress: bool = False,
) -> tuple[SequenceRefinement, StageOutcome[RefineSummary]]:
    """Refine the accepted poses of ``sequence`` (made or reused) and the stage's outcome.

    Args:
        dataset: the dataset folder.
        option: the ``map`` option (one of :data:`REFINE_MAPS`).
        sequence: the query sequence.
        localization: its localisation and that stage's outcome
            (:func:`~diffloc.pipeline.crossmodal_stage.localize_sequence`; after the
            storey-alias test, its answers and both stages' outputs).
        source: the map to render (:func:`field_source`, :func:`cloud_source`).
        config: ``task.refine``.
        show_progress: a progress bar over the queries.

    Raises:
        ValueError: ``option`` is not refinable (:func:`check_refinable`).
    """
    check_refinable(option)
    loc, loc_outcome = localization
    folder = crossmodal_folder(dataset) / option / f"refine_{sequence}"
    key = stage_key(
        {"refine": config.settings(), "record": REFINEMENT_RECORD},
        {
            "localization": loc_outcome.outputs,  # with the storey-alias test's when it ran
            "map": source.identity,
            **sequence_inputs(dataset, sequence, with_poses=False),
        },
    )
    command = Command("crossmodal", (f"dataset={dataset}", f"map={option}"))
    with open_stage(folder, "refine", command, LockLevel.UPDATED) as stage:
        summary = stage.reusable(key, RefineSummary)
        if summary is None:
            maps = source.load()
            arrays = _refine_all(maps, loc, dataset, sequence, config, show_progress)
            with atomic_open(stage.workdir() / "refinement.npz", "wb") as handle:
                write_npz(handle, arrays)
            refined = arrays["served"] != NO_MAP
            summary = RefineSummary(
                sequence=sequence,
                queries=len(loc.frames),
                localised=len(arrays["query"]),
                kept=int(arrays["kept"].sum()),
                median_cpu_ms=float(np.median(arrays["cpu_ms"][refined]))
                if refined.any()
                else None,
                load_average=list(os.getloadavg()),
            )
            summary = stage.commit(key, summary, ["refinement.npz"])
        outcome = stage.outcome(summary)
        return SequenceRefinement.load(folder / "refinement.npz"), outcome
