"""``diffloc task=crossmodal map=tls|cloud|mesh|nerf|images|hybrid``: the stages in order,
then the report.

Render poses -> map (``map=nerf``: the trained radiance-field submaps,
:mod:`diffloc.pipeline.crossmodal_nerf`) -> RGB-D database -> (``task.tune_retrieval``: its
NetVLAD tuned on the mapping images, :mod:`diffloc.pipeline.crossmodal_retrieval`) ->
localisation of each ``task.sequences`` (each a cached stage,
:mod:`diffloc.pipeline.crossmodal_stage`; ``map=images``: the database of the mapping images,
:mod:`diffloc.pipeline.crossmodal_images`, then the same localisation; ``map=hybrid``: both
databases of ``map=images`` and ``map=mesh``, then their union,
:mod:`diffloc.pipeline.crossmodal_hybrid`) -> (the maps of ``task.rerender.maps``, any of
``tls|cloud|mesh|nerf``, indoors ``mesh`` and ``cloud``: each pose found validated again on
the map rendered at it, a cached stage of its own, :mod:`diffloc.pipeline.crossmodal_rerender`;
its poses and verdicts replace the localisation's) -> (the maps of ``task.storey_alias.maps``, any
of ``tls|cloud|mesh``, indoors ``tls``: each accepted pose tested against renders on the other
floors, a cached stage of its own, :mod:`diffloc.pipeline.crossmodal_alias`; aliases are
refused) ->
(``task.refine.enabled``, ``map=nerf|tls|cloud``:
render-and-compare refinement of each sequence's accepted poses, a cached stage of its own,
:mod:`diffloc.pipeline.crossmodal_refine`) -> scores, ``results.md``, ``results.json``, TUM
files and plots in the run folder (:mod:`diffloc.pipeline.crossmodal_report`). A rerun with
the same settings reuses every stage; a changed ``task.localizer`` setting runs only the
localisation again.
"""

from __future__ import annotations

import json
import os
import platform
import time
from dataclasses import asdict
from pathlib import Path

from diffloc.crossmodal.database import RenderedDatabase
from diffloc.crossmodal.synthesize import RGBDMap
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.atomic import atomic_write_text
from diffloc.io.dataset import read_sequence
from diffloc.io.trajectory import write_tum
from diffloc.pipeline.crossmodal_alias import storey_alias_stage
from diffloc.pipeline.crossmodal_config import (
    CrossmodalTaskConfig,
    HybridMapConfig,
    ImageMapConfig,
    MeshMapConfig,
    NerfMapConfig,
    PointMapConfig,
    map_option,
)
from diffloc.pipeline.crossmodal_hybrid import build_hybrid_database
from diffloc.pipeline.crossmodal_images import build_image_database
from diffloc.pipeline.crossmodal_nerf import build_nerf_map
from diffloc.pipeline.crossmodal_refine import (
    MapSource,
    check_refinable,
    cloud_source,
    field_source,
    refine_sequence,
)
from diffloc.pipeline.crossmodal_report import (
    markdown_table,
    plot_retrieved,
    plot_trajectory,
    refinement_table,
    score_refinement,
    score_sequence,
    time_table,
)
from diffloc.pipeline.crossmodal_rerender import rerender_stage
from diffloc.pipeline.crossmodal_retrieval import tune_retrieval_stage
from diffloc.pipeline.crossmodal_stage import (
    MAP_OUTPUTS,
    MAPPING,
    build_rgbd_database,
    build_rgbd_map,
    crossmodal_folder,
    localize_sequence,
    render_pose_stage,
)
from diffloc.pipeline.nerf_config import TrainNerfConfig
from diffloc.pipeline.stage import StageOutcome

__all__ = ["run_crossmodal"]

STAGES = ("poses", "map", "database")
MapConfig = PointMapConfig | MeshMapConfig | NerfMapConfig | ImageMapConfig | HybridMapConfig


def run_crossmodal(
    dataset: str | os.PathLike,
    map_config: MapConfig,
    task: CrossmodalTaskConfig,
    out: str | os.PathLike,
    show_progress: bool = True,
    nerf: TrainNerfConfig | None = None,
) -> dict:
    """Run (or reuse) every stage and write the results into ``out``.

    Args:
        dataset: the dataset folder (point maps under ``map/``, the mapping sequence, the
            query sequences).
        map_config: the ``map`` node (``map=tls``, ``cloud``, ``mesh``, ``nerf``, ``images`` or
            ``hybrid``).
        task: the ``task`` node.
        out: the run folder.
        show_progress: progress bars (off when ``CI=true``).
        nerf: the root ``nerf`` node, which selects the fields of ``map=nerf`` (default
            settings if ``None``).

    Returns:
        The results (also ``out/results.json``): per sequence the figures of
        :func:`~diffloc.pipeline.crossmodal_report.score_sequence` and its files, the
        database size and hole share, and every stage's summary (``"stages"``).

    Raises:
        FileNotFoundError: a missing point map or sequence.
        ValueError: a point map without normals, without an upward normal, or with an empty
            corridor (the message names the file and ``task.poses``); ``task.tune_retrieval``
            with ``map=images`` or ``map=hybrid``.
        MissingStageError: ``map=images`` or ``map=hybrid`` without a surfel map (the message
            names the ``task=build_map`` command).
        MissingStageError: ``map=nerf`` and a submap serving a render pose is not trained
            with the ``nerf`` settings (the message names the ``task=train_nerf`` command).
    """
    start = time.perf_counter()
    dataset, out = Path(dataset), Path(out)
    option = map_option(map_config)
    if task.refine.enabled:
        check_refinable(option)
    if task.tune_retrieval and isinstance(map_config, ImageMapConfig | HybridMapConfig):
        raise ValueError(
            f"task.tune_retrieval tunes a rendered map's NetVLAD across the render/real gap; "
            f"map={option} holds the mapping images themselves: set task.tune_retrieval=false"
        )
    retrieval = None
    camera = read_sequence(dataset, MAPPING).camera.scaled(task.image_scale)
    if isinstance(map_config, ImageMapConfig):
        database = build_image_database(dataset, map_config, task.database, camera, show_progress)
        stages = {"database": database[1].summary.to_json()}
    elif isinstance(map_config, HybridMapConfig):
        real = build_image_database(
            dataset, map_config.images(), task.database, camera, show_progress
        )
        rendered, stages, _, _ = _rendered_database(
            dataset, map_config.mesh, task, camera, nerf, show_progress
        )
        database = build_hybrid_database(
            dataset, map_config, task.database, real, rendered, show_progress
        )
        stages = {
            **{f"mesh_{name}": summary for name, summary in stages.items()},
            "images_database": real[1].summary.to_json(),
            "database": database[1].summary.to_json(),
        }
    else:
        database, stages, (rgbd_map, map_outcome), poses_outcome = _rendered_database(
            dataset, map_config, task, camera, nerf, show_progress
        )
        if task.refine.enabled:
            source = _refine_source(dataset, map_config, map_outcome, task)
        rendered = (rgbd_map, map_outcome, database[0])
        render_poses = (map_config.point_map, poses_outcome)
        if task.tune_retrieval:
            tuned, retrieval = tune_retrieval_stage(
                dataset, option, task.retrieval, database, show_progress
            )
            database = (tuned, database[1])  # the database stage's outcome keys the rest
            stages["retrieval"] = retrieval.summary.to_json()
    db = database[0]
    prior = task.localizer_for(option).prior
    out.mkdir(parents=True, exist_ok=True)
    sequences = {}
    for name in task.sequences:
        loc, outcome = localize_sequence(
            dataset,
            option,
            name,
            task.every,
            task.localizer_for(option),
            database,
            show_progress,
            retrieval,
        )
        stages[f"localize_{name}"] = outcome.summary.to_json()
        if option in task.rerender.maps:
            rerendered, checked = rerender_stage(
                dataset,
                option,
                name,
                (loc, outcome),
                rendered,
                task.localizer_for(option),
                show_progress,
            )
            stages[f"rerender_{name}"] = checked.summary.to_json()
            loc = rerendered.apply(loc)  # the re-render's poses and verdicts
            outcome = StageOutcome(outcome.summary, {**outcome.outputs, **checked.outputs})
        if option in task.storey_alias.maps:
            aliases, tested = storey_alias_stage(
                dataset,
                option,
                name,
                (loc, outcome),
                rendered,
                render_poses,
                task.localizer_for(option),
                task.storey_alias.ratio,
                show_progress,
            )
            stages[f"alias_{name}"] = tested.summary.to_json()
            loc = aliases.apply(loc)  # the storey aliases are no longer accepted
            # what comes after keys on both records
            outcome = StageOutcome(outcome.summary, {**outcome.outputs, **tested.outputs})
        seq = read_sequence(dataset, name)  # ground truth: scoring only
        T_gt = seq.T_wc[loc.frames]
        scores = score_sequence(loc, T_gt, db.T_wc, task.poses.spacing_m, task.loose_m)
        accepted = loc.accepted.astype(bool)
        tum = out / f"trajectory_{name}.tum"
        write_tum(tum, seq.timestamps[loc.frames][accepted], loc.T_wc[accepted])
        files = {
            "trajectory_tum": tum,
            "retrieved_png": plot_retrieved(
                out / f"retrieved_{name}.png", loc, seq, db.rgb, task.plot_queries
            ),
            "trajectory_png": plot_trajectory(
                out / f"trajectory_{name}.png", loc, T_gt, f"{name} in {option} ({dataset.name})"
            ),
        }
        if task.refine.enabled:
            refinement, refined = refine_sequence(
                dataset, option, name, (loc, outcome), source, task.refine, show_progress
            )
            stages[f"refine_{name}"] = refined.summary.to_json()
            scores["refine"] = score_refinement(loc, refinement, T_gt, task.loose_m)
            files["refined_tum"] = out / f"trajectory_{name}_refined.tum"
            refined_T_wc = refinement.answers(loc)
            write_tum(
                files["refined_tum"], seq.timestamps[loc.frames][accepted], refined_T_wc[accepted]
            )
        sequences[name] = {**scores, "files": {k: str(v) for k, v in files.items()}}
    results = {
        "dataset": str(dataset),
        "map": option,
        "map_settings": asdict(map_config),
        "database_images": db.num_images,
        "hole_share": float(db.holes.mean()),
        "image_size": f"{db.camera.width}x{db.camera.height}",
        "loose_m": task.loose_m,
        "every": task.every,
        "prior": None if prior is None else asdict(prior),
        "refine": asdict(task.refine) if task.refine.enabled else None,
        "sequences": sequences,
        "machine": f"{platform.node()} {os.cpu_count()} cores, load {os.getloadavg()}",
        "wall_s": round(time.perf_counter() - start, 1),
        "stages": stages,
    }
    atomic_write_text(out / "results.json", json.dumps(results, indent=2) + "\n")
    atomic_write_text(out / "results.md", _markdown(results))
    return results


def _refine_source(
    dataset: Path,
    map_config: PointMapConfig | MeshMapConfig | NerfMapConfig,
    map_outcome: StageOutcome,
    task: CrossmodalTaskConfig,
) -> MapSource:
    """The map stage's output the refinement renders (``map=nerf``: the submap fields;
    ``map=tls|cloud``: the coloured cloud; :func:`check_refinable` refused the others)."""
    output = MAP_OUTPUTS[type(map_config)]
    path = crossmodal_folder(dataset) / map_option(map_config) / "map" / output
    make = field_source if isinstance(map_config, NerfMapConfig) else cloud_source
    return make(path, map_outcome.outputs[output], task.refine)


def _rendered_database(
    dataset: Path,
    map_config: PointMapConfig | MeshMapConfig | NerfMapConfig,
    task: CrossmodalTaskConfig,
    camera: PinholeCamera,
    nerf: TrainNerfConfig | None,
    show_progress: bool,
) -> tuple[
    tuple[RenderedDatabase, StageOutcome],
    dict[str, dict],
    tuple[RGBDMap, StageOutcome],
    StageOutcome,
]:
    """Render poses -> map -> database of a rendered map (each made or reused): the database
    with its outcome, the three stages' summaries by :data:`STAGES` name, the map (its
    renderer) with the map stage's outcome, and the render-pose stage's outcome."""
    option = map_option(map_config)
    poses = render_pose_stage(
        dataset, map_config.point_map, task.poses_for(map_config.point_map), option
    )
    if isinstance(map_config, NerfMapConfig):
        rgbd_map = build_nerf_map(dataset, map_config, nerf or TrainNerfConfig(), poses)
    else:
        rgbd_map = build_rgbd_map(dataset, map_config, task.image_scale, show_progress)
    database = build_rgbd_database(
        dataset, map_config, task.database, rgbd_map, poses, camera, show_progress
    )
    outcomes = (poses[1], rgbd_map[1], database[1])
    stages = {
        name: outcome.summary.to_json() for name, outcome in zip(STAGES, outcomes, strict=True)
    }
    return database, stages, rgbd_map, poses[1]


def _markdown(results: dict) -> str:
    loose = results["loose_m"]
    prior = results["prior"]
    return "\n".join(
        [
            f"# Rendered-database localisation in `map={results['map']}` ({results['dataset']})",
            "",
            f"Database: {results['database_images']} images of {results['image_size']}, "
            f"hole share {100 * results['hole_share']:.1f} %; queries: every "
            f"{results['every']}-th frame of each sequence; pose prior "
            + ("off." if prior is None else f"on: {prior}."),
            "",
            markdown_table(results["sequences"], loose),
            "",
            "Time per query (the localisation stage's record; CPU: the process's, so on one "
            "thread the work done; stages: mean CPU ms per query, matching and PnP summed over "
            "the candidates matched):",
            "",
            time_table(results["sequences"]),
            "",
            f"Accepted: a pose was found and passed the validation. Precision: share of the "
            f"accepted poses within {loose:g} m / 30 deg. From prior: accepted poses whose "
            "reference the pose prior put first (task.localizer.prior), wrong ones in brackets. "
            "Rates: share of all queries accepted "
            "within the bound (a query not localised is a failure). Retrieval: the top-1 "
            "render lies within the render spacing and 45 deg of the query. mATE: mean "
            "position error of the accepted queries. ms/query: median wall time (features, "
            "retrieval, matching, PnP, and the re-render check where `task.rerender` ran: "
            "stages.rerender_<sequence> in results.json) when the localisation ran (its load "
            "average is in results.json, stages.localize_<sequence>); machine: "
            f"{results['machine']}.",
            "",
            "Files per sequence: `trajectory_<sequence>.tum` (accepted poses; "
            "`evo_ape tum <truth> trajectory_<sequence>.tum`), `retrieved_<sequence>.png` "
            "(query left, the render its pose came from, or its top-1 render, right) and "
            "`trajectory_<sequence>.png` (top-down, ground truth in black).",
            "",
            *_refinement_markdown(results),
        ]
    )


def _refinement_markdown(results: dict) -> list[str]:
    """The refinement's section of ``results.md`` (none when ``task.refine`` was off)."""
    refine = results["refine"]
    if refine is None:
        return []
    render, check = refine["render"], refine["check"]
    rule = (
        f"cost drop > {100 * render['min_improvement']:g} % and correlation >= "
        f"{render['min_correlation']:g}"
    )
    if refine["verify"]:
        rule += (
            f", and the match check at {check['width']} px width (>= {check['min_inliers']} "
            f"XFeat matches aligned within {check['inlier_px']:g} px, >= "
            f"{100 * check['min_fraction']:g} % of them, >= {check['min_gain']:g} x the start's)"
        )
    return [
        "Render-and-compare refinement of the accepted poses (`task.refine`; before -> after; "
        f"queries at {refine['image_scale']:g} of their size, levels {render['levels']}, "
        f"{render['iterations']} LM iterations per level; a refined pose is kept if {rule}; "
        "rates over all queries, errors over the localised ones; kept (wrong): refined poses "
        "kept, of them ending farther from the true position than they started; ended closer: "
        "refinements that ended nearer the true position than they started, kept or not; "
        "had all been kept: the refined queries' errors without the acceptance rule; CPU ms: "
        "median process CPU per refined query, the appearance fit and the check included; its "
        "load average is in results.json, stages.refine_<sequence>):",
        "",
        refinement_table(results["sequences"], results["loose_m"]),
        "",
        "`trajectory_<sequence>_refined.tum`: the accepted poses after the refinement.",
        "",
    ]
