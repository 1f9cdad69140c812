"""The ``diffloc`` command: one Hydra app whose ``task=`` selects the job.

Examples:
    diffloc                                         # the main job on the default indoor scene
    diffloc task=simulate scene=outdoor scene.seed=3 out_dir=data/courtyard
    diffloc -m task=simulate scene.seed=0,1,2       # a multirun sweep over seeds
    diffloc task=build_map dataset=data/indoor_seed0 # surfel map + coloured point maps
    diffloc task=build_db db.noise_sigma=0.2         # visual database with noisy poses
    diffloc task=optimize_db db.noise_sigma=0.2      # surfel reprojection optimisation
    diffloc task=update_db task.sequence=query_lane  # add a sequence to the built database
    diffloc task=calibrate_rig                      # camera extrinsic + time offset of a database
    diffloc task=relocalize reloc.method.points=F    # relocalise the query sequences
    diffloc task=relocalize features=orb retriever=bow  # swap extractor and retriever (groups)
    diffloc task=train_nerf nerf.submap=3            # one radiance-field submap
    diffloc -m +experiment=table3_noise              # a committed table's sweep
    diffloc task=export_colmap task.database=optimized  # the database as a COLMAP model
    diffloc task=crossmodal map=tls                 # seed 2: localise in renders of a map
    diffloc task=crossmodal map=images              # ... in the mapping images (comparison)
    diffloc task=crossmodal map=nerf                # ... of the trained radiance-field submaps
    diffloc task=crossmodal map=hybrid              # ... in both: images + uncovered mesh renders
    diffloc task=main                               # all of the above, each stage cached

Errors: a checked error (an ``OSError`` such as a missing dataset or database, a
``ValueError`` such as a bad value or an unknown config key) prints one line, ``error: ...``,
and exits with status 1; ``HYDRA_FULL_ERROR=1`` shows Hydra's full traceback instead. A
message that names a command to run carries the user's own overrides (``scene=outdoor``,
``dataset=...``). Any other exception is a bug and keeps its traceback.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from diffloc.benchmark import peak_rss_mb
from diffloc.config import CONF_DIR, check_known_keys, register_configs, to_object
from diffloc.io.atomic import atomic_write_text
from diffloc.io.lock import lock_config
from diffloc.pipeline.build_map import MapSummary, build_maps
from diffloc.pipeline.colmap_stage import ColmapExport, export_colmap
from diffloc.pipeline.crossmodal_config import map_option
from diffloc.pipeline.crossmodal_refine import check_refinable
from diffloc.pipeline.crossmodal_stage import crossmodal_folder
from diffloc.pipeline.crossmodal_task import run_crossmodal
from diffloc.pipeline.database_stage import build_database, optimize_database
from diffloc.pipeline.database_summary import BuiltDatabase, OptimizedDatabase
from diffloc.pipeline.hints import Command, CommandHint, MissingStageError, override_key
from diffloc.pipeline.nerf_heldout import heldout_line
from diffloc.pipeline.nerf_stage import NerfSummary, train_nerf_submap
from diffloc.pipeline.reloc_stage import relocalize_dataset
from diffloc.pipeline.rig_stage import RigCalibrationSummary, calibrate_database_rig
from diffloc.pipeline.update_stage import UpdateSummary, update_database
from diffloc.sim.dataset import simulate_dataset, validate_scene_config


def run_simulate(cfg: DictConfig) -> Path:
    """``task=simulate``: write (or reuse) the dataset folder ``cfg.out_dir``."""
    scene = OmegaConf.to_object(cfg.scene)
    out_dir = simulate_dataset(
        scene, Path(cfg.out_dir), overwrite=cfg.task.overwrite, show_progress=cfg.progress
    )
    print(f"dataset: {out_dir}")
    print(f"preview: {out_dir / 'preview.png'}")
    return out_dir


def run_build_map(cfg: DictConfig) -> MapSummary:
    """``task=build_map``: surfel map, coloured point maps and preview under ``dataset/map``."""
    summary = build_maps(
        Path(cfg.dataset),
        OmegaConf.to_object(cfg.task),
        to_object(cfg.map),
        show_progress=cfg.progress,
    )
    print(f"surfels: {summary.surfels} from {summary.source}")
    print(f"surfel_map: {summary.surfel_map}")
    for name, point_map in summary.point_maps.items():
        print(f"{name}: {point_map['path']}")
    print(f"preview: {summary.preview}")
    return summary


def run_build_db(cfg: DictConfig) -> BuiltDatabase:
    """``task=build_db``: the visual database of ``dataset`` (noisy poses if ``db.noise_sigma``)."""
    summary = build_database(Path(cfg.dataset), to_object(cfg.db), cfg.progress)
    print(
        f"database: {summary.database} ({summary.keyframes} keyframes, "
        f"{summary.map_points} map points, keyframe position RMSE "
        f"{summary.kf_pos_rmse_m:.3f} m)"
    )
    return summary


def run_optimize_db(cfg: DictConfig) -> OptimizedDatabase:
    """``task=optimize_db``: surfel reprojection optimisation of the ``build_db`` database."""
    summary = optimize_database(Path(cfg.dataset), to_object(cfg.db), cfg.progress)
    verdict = "accepted" if summary.accepted else "NOT accepted, built poses kept"
    print(
        f"optimized: {summary.database} ({verdict}: {summary.check_reason}; keyframe "
        f"position RMSE {summary.kf_pos_rmse_before_m:.3f} m -> "
        f"{summary.kf_pos_rmse_after_m:.3f} m)"
    )
    return summary


def run_update_db(cfg: DictConfig) -> UpdateSummary:
    """``task=update_db``: add the frames of ``task.sequence`` to the ``build_db`` database."""
    summary = update_database(
        Path(cfg.dataset), to_object(cfg.db), OmegaConf.to_object(cfg.task), cfg.progress
    )
    before, added, after = summary.before, summary.after_adding, summary.after_culling
    culled = summary.culled
    print(
        f"updated: {summary.database} with {summary.images} images of "
        f"{summary.sequence}: keyframes {before['keyframes']} -> {added['keyframes']} -> "
        f"{after['keyframes']} ({culled['keyframes']} culled), map points "
        f"{before['map_points']} -> {added['map_points']} -> {after['map_points']} "
        f"({culled['points_unconfirmed']} unconfirmed, {culled['points_of_culled_keyframes']} "
        "with culled keyframes)"
    )
    return summary


def run_calibrate_rig(cfg: DictConfig) -> RigCalibrationSummary:
    """``task=calibrate_rig``: the camera extrinsic and time offset of the ``build_db`` database."""
    summary = calibrate_database_rig(
        Path(cfg.dataset), to_object(cfg.db), OmegaConf.to_object(cfg.task.calibration)
    )
    std_cm = 100.0 * math.sqrt(sum(s * s for s in summary.std[:3]))
    print(
        f"rig calibration: extrinsic correction {summary.correction_cm:.2f} cm / "
        f"{summary.correction_deg:.3f} deg (translation std {std_cm:.2f} cm), time offset "
        f"{summary.dt_s * 1e3:.2f} ms, {summary.num_pairs} surfel pairs, "
        f"{summary.iterations} iterations ({summary.reason})"
    )
    print(f"results: {Path(summary.database).parent / 'rig_calibration.json'}")
    if summary.urdf is not None:
        print(f"corrected rig: {summary.urdf}")
    return summary


def run_export_colmap(cfg: DictConfig) -> ColmapExport:
    """``task=export_colmap``: a saved database as a COLMAP TEXT model."""
    export = export_colmap(Path(cfg.dataset), to_object(cfg.db), OmegaConf.to_object(cfg.task))
    summary = export.summary
    print(
        f"COLMAP model: {export.model} ({summary.images} images, {summary.points} "
        f"points, {summary.observations} observations; colours: {summary.colors})"
        + (" up to date, reused" if export.reused else "")
    )
    return export


def _results_dir(cfg: DictConfig, fallback: Path | None = None) -> Path:
    """``task.out_dir``, else the Hydra run folder, else ``fallback`` (``<dataset>/reloc``)."""
    if cfg.task.out_dir:
        return Path(cfg.task.out_dir)
    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    return fallback or Path(cfg.dataset) / "reloc"


def _print_results(results: dict, out: Path) -> None:
    """The metrics table, the plot paths and where ``results.json`` is."""
    print(results["table"])
    for name, entry in results["sequences"].items():
        for kind, path in entry["plots"].items():
            print(f"{name} {kind}: {path}")
    print(f"results: {out / 'results.json'}")


def run_relocalize(cfg: DictConfig) -> dict:
    """``task=relocalize``: relocalise the query sequences; print the table and plot paths."""
    out = _results_dir(cfg)
    results = relocalize_dataset(
        Path(cfg.dataset),
        to_object(cfg.db),
        to_object(cfg.reloc),
        out,
        show_progress=cfg.progress,
    )
    _print_results(results, out)
    return results


def run_main(cfg: DictConfig) -> dict:
    """``task=main``: simulate if needed, map, database, optimisation, relocalisation."""
    start = time.perf_counter()
    dataset = Path(cfg.dataset)
    if not (dataset / "dataset.json").is_file():
        scene = OmegaConf.to_object(cfg.scene)
        simulate_dataset(scene, dataset, show_progress=cfg.progress)
    build_maps(
        dataset,
        OmegaConf.to_object(cfg.task.build_map),
        to_object(cfg.map),
        show_progress=cfg.progress,
    )
    db_cfg = to_object(cfg.db)
    run_build_db(cfg)  # each stage is reused while its config and inputs are unchanged
    if cfg.task.optimize:
        run_optimize_db(cfg)
    reloc = to_object(cfg.reloc)
    reloc.database = "optimized" if cfg.task.optimize else "database"
    out = _results_dir(cfg)
    results = relocalize_dataset(dataset, db_cfg, reloc, out, show_progress=cfg.progress)
    results["peak_rss_mb"] = peak_rss_mb()
    results["wall_s"] = round(time.perf_counter() - start, 1)
    atomic_write_text(out / "results.json", json.dumps(results, indent=2) + "\n")
    _print_results(results, out)
    print(f"peak memory {results['peak_rss_mb']:.0f} MB, {results['wall_s']:.0f} s")
    return results


def run_crossmodal_task(cfg: DictConfig) -> dict:
    """``task=crossmodal``: localise the query sequences in a database rendered from ``map``."""
    map_config = to_object(cfg.map)
    fallback = crossmodal_folder(cfg.dataset) / map_option(map_config) / "results"
    out = _results_dir(cfg, fallback)
    results = run_crossmodal(
        Path(cfg.dataset),
        map_config,
        to_object(cfg.task),
        out,
        show_progress=cfg.progress,
        nerf=to_object(cfg.nerf),
    )
    print((out / "results.md").read_text(encoding="utf-8"))
    print(f"results: {out / 'results.json'}")
    return results


def run_train_nerf(cfg: DictConfig) -> NerfSummary:
    """``task=train_nerf``: train one radiance-field submap under ``<dataset>/nerf``."""
    summary = train_nerf_submap(Path(cfg.dataset), to_object(cfg.nerf), cfg.progress)
    print(f"submap {summary.submap} of {summary.submaps}: {summary.steps} steps")
    print(f"field: {summary.field}")
    print(heldout_line(summary.heldout_scores, summary.heldout_note))
    return summary


TASKS: dict[str, Callable[[DictConfig], object]] = {
    "simulate": run_simulate,
    "build_map": run_build_map,
    "build_db": run_build_db,
    "optimize_db": run_optimize_db,
    "update_db": run_update_db,
    "calibrate_rig": run_calibrate_rig,
    "relocalize": run_relocalize,
    "export_colmap": run_export_colmap,
    "main": run_main,
    "train_nerf": run_train_nerf,
    "crossmodal": run_crossmodal_task,
}


TASK_MAPS: dict[str, tuple[str, ...]] = {
    "crossmodal": ("tls", "cloud", "mesh", "images", "nerf", "hybrid")
}
"""The ``map`` options of the tasks that render a map; every other task takes ``map=surfel``."""


MAKE_DATASET = ("simulate", "main")
"""Tasks that write the dataset folder; every other task reads an existing one."""


VALUE_NODES = ("map", "db", "reloc", "nerf", "task", "stage")
"""Config nodes whose schemas check their ranges and names when built (``__post_init__``)."""


def _build_node(node: DictConfig, path: str) -> None:
    """Build the typed node ``node`` at key ``path``; a bad value's message names its full key.

    A nested schema checks its own fields without knowing where it sits (``max_keypoints must
    be ...``); the error is raised again from the deepest node that fails, its key in front
    (``db.xfeat.max_keypoints must be ...``).
    """
    try:
        to_object(node)
    except ValueError as exc:
        for key in node.keys():
            if OmegaConf.is_missing(node, key) or OmegaConf.is_interpolation(node, key):
                continue
            child = node[key]
            if isinstance(child, DictConfig) and (
                "_target_" in child or dataclasses.is_dataclass(OmegaConf.get_type(child))
            ):
                _build_node(child, f"{path}.{key}")
        message = str(exc)
        if message.startswith(f"{path}.") or message.startswith(f"{path} "):
            raise
        first, _, rest = message.partition(" ")
        field_name = first.removeprefix(f"{OmegaConf.get_type(node).__name__}.")
        if field_name in node:
            raise ValueError(f"{path}.{field_name} {rest}") from exc
        raise ValueError(f"{path}: {message}") from exc


def check_map_option(task: str, option: str) -> None:
    """Refuse a ``map`` option the task cannot use (:data:`TASK_MAPS`).

    Raises:
        ValueError: one line naming the map options of every task.

    Example:
        >>> try:
        ...     check_map_option("main", "tls")
        ... except ValueError as error:
        ...     print(str(error).split(": ")[0])
        task=main cannot use map=tls
    """
    allowed = TASK_MAPS.get(task, ("surfel",))
    if option in allowed:
        return
    rendered = "; ".join(f"task={name} takes {_choices(maps)}" for name, maps in TASK_MAPS.items())
    raise ValueError(
        f"task={task} cannot use map={option}: {rendered}; every other task takes map=surfel"
    )


def _choices(options: tuple[str, ...]) -> str:
    """``map=a, map=b or map=c``."""
    words = [f"map={o}" for o in options]
    return " or ".join([", ".join(words[:-1]), words[-1]] if len(words) > 1 else words)


def check_values(cfg: DictConfig) -> None:
    """Check every range and name of the config before any work starts.

    Builds each typed node once (its dataclass checks run: ``reloc.max_trans_m``,
    ``task.render_batch``, ``task.clouds`` names, ...) and, for the tasks that simulate, the
    scene (``scene.map.voxel_size_m``, every sequence's trajectory), so a bad value fails in
    seconds instead of after the stages before it.

    Raises:
        ValueError: the first bad value; the message names its full key.
    """
    for key in VALUE_NODES:
        if key in cfg:
            _build_node(cfg[key], key)
    option = map_option(to_object(cfg.map))
    check_map_option(cfg.task.name, option)
    if cfg.task.name == "crossmodal" and cfg.task.refine.enabled:
        check_refinable(option)
    if cfg.task.name in MAKE_DATASET:
        validate_scene_config(OmegaConf.to_object(cfg.scene))


def run(cfg: DictConfig) -> object:
    """Run the task named by ``cfg.task.name`` on a composed config.

    Raises:
        UnknownKeyError: the config holds a key no schema declares (``+scene.max_frames=5``).
        ValueError: a value out of range or an unknown name (:func:`check_values`), before any
            work.
        MissingStageError: a task that reads ``dataset`` finds no ``dataset.json`` there; the
            message names the ``task=simulate`` command that writes it.
        ValueError: an unknown task name.
    """
    check_known_keys(cfg)
    name = cfg.task.name
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; choose one of {sorted(TASKS)}")
    check_values(cfg)
    description = Path(cfg.dataset) / "dataset.json"
    if name not in MAKE_DATASET and not description.is_file():
        raise MissingStageError(description, Command("simulate", (), (f"out_dir={cfg.dataset}",)))
    with lock_config(OmegaConf.to_object(cfg.stage)):
        return TASKS[name](cfg)


CHECKED_ERRORS = (OSError, ValueError)
"""Errors of bad input or a missing stage: one line on the command line (module docstring)."""


def _users_overrides(task: str) -> list[str] | None:
    """The overrides the user typed, for a command that runs ``task``.

    ``task=...`` is left out, and so are ``task.*`` settings unless ``task`` is the task that
    ran, and ``map=...`` / ``map.*`` when ``task`` cannot use the map that ran (``task=crossmodal
    map=nerf`` names ``task=train_nerf``, which takes ``map=surfel``). ``None`` outside a Hydra
    run (the command line is unknown).
    """
    if not HydraConfig.initialized():
        return None
    typed = HydraConfig.get().overrides.task
    choices = HydraConfig.get().runtime.choices
    same = task == choices.get("task")
    same_map = choices.get("map") in TASK_MAPS.get(task, ("surfel",))
    return [
        word
        for word in typed
        if override_key(word) != "task"
        and (same or not override_key(word).startswith("task."))
        and (same_map or override_key(word).split(".")[0] not in ("map", "map/scene"))
    ]


def _error_line(error: Exception) -> str:
    """The one-line message of a checked error; a command it names has the user's overrides."""
    if isinstance(error, CommandHint):
        message = error.render(_users_overrides(error.command.task))
    else:
        message = str(error)
    return " ".join(line.strip() for line in message.splitlines())


def _show_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: object = None,
    line: str | None = None,
) -> None:
    """``warnings.showwarning`` of the command: ``warning: <message>`` on stderr."""
    print(f"warning: {message}", file=sys.stderr)


register_configs()


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def main(cfg: DictConfig) -> None:
    """Entry point of the ``diffloc`` console script.

    A checked error prints one line and exits with status 1 (unless ``HYDRA_FULL_ERROR=1``);
    in a multirun that stops the sweep at the failed job. Warnings print as one line each,
    without the source line that raised them.
    """
    with warnings.catch_warnings():
        warnings.showwarning = _show_warning
        try:
            run(cfg)
        except CHECKED_ERRORS as error:
            if os.environ.get("HYDRA_FULL_ERROR") == "1":
                raise
            sys.exit(f"error: {_error_line(error)}")


if __name__ == "__main__":
    main()
