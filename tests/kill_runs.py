"""Stage runs killed at random points (SIGKILL), for the kill test and ``experiments/``.

:func:`killed_run` starts a child that runs one stage on a dataset folder and kills it after a
given delay (if it has not finished) with SIGKILL, the way the OOM killer or a lost machine
would: no ``finally`` block, no ``atexit`` handler runs. Children come from a fork server
(``multiprocessing``'s ``forkserver``, with this module preloaded): a fork of the test process
itself could hang, since OpenMP's thread pool does not survive a fork once torch has used it.
:func:`stage_outputs` reads back every output a stage's record lists, byte for byte.
"""

from __future__ import annotations

import json
import multiprocessing
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from diffloc.cli import run
from diffloc.config import compose_config, to_object
from diffloc.pipeline.build_map import BuildMapConfig, build_maps
from diffloc.pipeline.colmap_stage import ExportColmapTaskConfig, export_colmap
from diffloc.pipeline.crossmodal_stage import TIMING_ARRAYS
from diffloc.pipeline.database_select import updated_dir
from diffloc.pipeline.database_stage import (
    DatabaseConfig,
    build_database,
    database_dir,
    optimize_database,
)
from diffloc.pipeline.nerf_stage import train_nerf_submap
from diffloc.pipeline.update_stage import UpdateTaskConfig, update_database
from diffloc.sim.dataset import simulate_dataset
from tests.conftest import FINE_SURFELS, TINY, TINY_NERF, scene_config

_NOISY = DatabaseConfig(noise_sigma=0.05)
NOISY_DB = replace(
    _NOISY,
    optim=replace(_NOISY.optim, min_pairs=5),
    optim_check=replace(_NOISY.optim_check, accept="always"),
)
"""A database with noisy poses whose optimisation runs on the tiny scene (few surfel pairs)."""

UPDATE_TASK = UpdateTaskConfig(sequence="query_lane")

STAGE_CONFIGS = {
    "build_map": BuildMapConfig(point_maps=["tls_map"], preview_frames=1),
    "build_db": NOISY_DB,
    "optimize_db": NOISY_DB,
    "update_db": NOISY_DB,
    "export_colmap": NOISY_DB,
    "train_nerf": to_object(compose_config(["task=train_nerf", *TINY_NERF]).nerf),
    "simulate": TINY + ["scene=indoor"],
}
"""The stage runs that are killed: a map with a coloured point map, a noisy database, its
optimisation, its update with ``query_lane``, its COLMAP export (``<database_dir>/colmap/
database``), the tiny radiance field of submap 0 (``<dataset>/nerf/submap_0``), the tiny indoor
dataset (its overrides; ``root`` is then the dataset folder to write)."""

EXPORT_TASK = ExportColmapTaskConfig(overwrite=True)
"""``task.overwrite=true``: a kill case removes the record to make the stage run again, which
leaves a model folder that holds no export of the stage (refused without it)."""

NOISY_DB_OVERRIDES = ("db.noise_sigma=0.05", "db.optim.min_pairs=5", "db.optim_check.accept=always")
""":data:`NOISY_DB` as ``diffloc`` overrides."""
_CROSSMODAL = (
    "task=crossmodal",
    "task.sequences=[query_same]",
    "task.every=2",
    "task.image_scale=1.0",
    "task.localizer.validation.theta_in=30",
)
_SMALL_MESH = (
    "map.texture.reconstruction.poisson_depth=7",
    "map.texture.reconstruction.target_faces=6000",
    "map.texture.atlas_size=256",
)
TASK_RUNS = {
    "calibrate_rig": ("task=calibrate_rig", *NOISY_DB_OVERRIDES),
    "relocalize": (
        "task=relocalize",
        *NOISY_DB_OVERRIDES,
        "retriever=bow",
        "reloc.database=database",
        "reloc.sequences=[query_same]",
    ),
    "crossmodal_tls": (*_CROSSMODAL, "map=tls"),
    "crossmodal_mesh": (*_CROSSMODAL, "map=mesh", "map.point_map=tls_map", *_SMALL_MESH),
    "crossmodal_images": (*_CROSSMODAL, "map=images"),
    "crossmodal_nerf": (*_CROSSMODAL, "map=nerf", "map.point_map=tls_map", *TINY_NERF),
}
"""The stages killed as a ``diffloc`` command on the tiny scene (``dataset=`` and, for
``relocalize``, ``task.out_dir=<dataset>/reloc_out`` added): the rig calibration and a
relocalisation of the noisy database, and ``task=crossmodal`` with each map that runs on the
tiny scene, whose stages (render poses, map, database, localisation) a kill may cut anywhere
(render poses on the TLS map: the tiny lidar map has no free corridor, so ``map=cloud``, which
places them on it, stops with that error before any work)."""

PREREQUISITES = {
    "optimize_db": ("build_db",),
    "update_db": ("build_db",),
    "export_colmap": ("build_db",),
    "calibrate_rig": ("build_db",),
    "relocalize": ("build_db",),
    "crossmodal_nerf": ("train_nerf", "train_nerf_1"),
}
"""The stages each killed stage needs to have run first (on the same settings)."""

CROSSMODAL_RECORDS = ("render_poses", "crossmodal_map", "rgbd_database", "localize")
"""The records of the stages of ``task=crossmodal`` (under ``<dataset>/crossmodal``)."""


def run_stage(stage: str, root: Path) -> object:
    """Run ``stage`` (a key of :data:`STAGE_CONFIGS`) on ``root``; what it returns (its typed
    summary; the dataset folder for ``simulate``)."""
    if stage in TASK_RUNS:
        out = (f"task.out_dir={stage_folder(stage, root)}",) if stage == "relocalize" else ()
        return run(compose_config([*TINY, f"dataset={root}", *TASK_RUNS[stage], *out]))
    if stage == "train_nerf_1":  # the second submap, which map=nerf renders too
        return train_nerf_submap(root, replace(STAGE_CONFIGS["train_nerf"], submap=1), False)
    config = STAGE_CONFIGS[stage]
    if stage == "build_map":
        return build_maps(root, config, FINE_SURFELS, show_progress=False)
    if stage == "simulate":
        return simulate_dataset(scene_config(config), root, show_progress=False)
    if stage == "optimize_db":
        return optimize_database(root, config, show_progress=False)
    if stage == "update_db":
        return update_database(root, config, UPDATE_TASK, show_progress=False)
    if stage == "export_colmap":
        return export_colmap(root, config, EXPORT_TASK)
    if stage == "train_nerf":
        return train_nerf_submap(root, config, show_progress=False)
    return build_database(root, config, show_progress=False)


def stage_folder(stage: str, root: Path) -> Path:
    """The folder ``stage`` writes into."""
    if stage == "build_map":
        return root / "map"
    if stage == "simulate":
        return root
    if stage == "update_db":
        return updated_dir(root, STAGE_CONFIGS[stage], UPDATE_TASK.sequence)
    if stage == "export_colmap":
        return database_dir(root, STAGE_CONFIGS[stage]) / "colmap"
    if stage == "train_nerf":
        return root / "nerf" / f"submap_{STAGE_CONFIGS[stage].submap}"
    if stage == "relocalize":
        return root / "reloc_out"
    if stage.startswith("crossmodal_"):
        return root / "crossmodal"
    return database_dir(root, NOISY_DB)


def stage_record(stage: str, root: Path) -> Path:
    """The record ``stage`` writes (``export_colmap`` names it after its model folder,
    ``calibrate_rig`` writes ``rig_calibration.json``)."""
    names = {"export_colmap": f"{stage}_{EXPORT_TASK.database}", "calibrate_rig": "rig_calibration"}
    return stage_folder(stage, root) / f"{names.get(stage, stage)}.json"


def stage_records(stage: str, root: Path) -> list[Path]:
    """Every record ``stage`` writes: those of the stages of ``task=crossmodal`` that exist,
    else :func:`stage_record`."""
    if not stage.startswith("crossmodal_"):
        return [stage_record(stage, root)]
    folder = stage_folder(stage, root)
    return sorted(p for p in folder.rglob("*.json") if p.stem in CROSSMODAL_RECORDS)


def work_started(stage: str, root: Path) -> str:
    """The ``after_glob`` of :func:`killed_run` that matches ``stage``'s work folder on ``root``
    (it exists from when the stage starts its work until its commit)."""
    folder = stage_folder(stage, root).relative_to(root.parent)
    return f"{folder.as_posix()}/.tmp-{stage}-*"


def folder_files(folder: Path) -> dict[str, bytes]:
    """The bytes of every file under ``folder`` (hidden lock files left out), by path."""
    return {
        p.relative_to(folder).as_posix(): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != ".diffloc.lock"
    }


_FORK_SERVER = multiprocessing.get_context("forkserver")
_FORK_SERVER.set_forkserver_preload([__name__])


def _run_in_child(stage: str, root: str) -> None:
    try:
        run_stage(stage, Path(root))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent by the status
        print(f"{stage} failed: {exc!r}", file=sys.stderr, flush=True)
        sys.exit(1)


def killed_run(
    stage: str, root: Path, delay_s: float | None, *, after_glob: str | None = None
) -> tuple[bool, float]:
    """Run ``stage`` on ``root`` in a child process, SIGKILLed after ``delay_s`` seconds.

    The child is forked from the fork server, which has imported everything already, so the
    delay falls on the stage's own work; it exits with status 1 (the error on stderr) if the
    stage raised.

    Args:
        stage: a key of :data:`STAGE_CONFIGS`.
        root: the dataset folder.
        delay_s: seconds to let it run before the kill; ``None``: let it finish.
        after_glob: start the ``delay_s`` clock only once a path matching this pattern exists
            beside ``root`` (polled every 2 ms), e.g. the stage's temporary folder; the kill
            then lands while that path is being written, however the machine's load shifts
            the stage's timing.

    Returns:
        ``(killed, seconds until it exited or was killed)``.

    Raises:
        RuntimeError: the child failed on its own.
    """
    child = _FORK_SERVER.Process(target=_run_in_child, args=(stage, str(root)))
    child.start()  # returns once the child is forked (the server is up)
    start = time.perf_counter()
    if after_glob is not None:
        while child.is_alive() and not any(Path(root).parent.glob(after_glob)):
            time.sleep(0.002)
    child.join(delay_s)
    if child.exitcode is None:
        child.kill()
        child.join()
        return True, time.perf_counter() - start
    if child.exitcode != 0:
        raise RuntimeError(f"{stage} on {root} failed in the child (see stderr)")
    return False, time.perf_counter() - start


TIMED = {".png", ".md", ".json"}
"""Suffixes of relocalisation reports (timings, plots of them): not compared."""


def _comparable(stage: str, path: Path) -> bytes | None:
    """What two runs of ``stage`` must agree on in output file ``path``: its bytes, but a
    localisation archive without its times (``time_ms``; ``TIMING_ARRAYS`` of
    ``task=crossmodal``'s) and none of ``relocalize``'s reports (its poses are; ``None``: not
    compared)."""
    if stage == "relocalize" and path.suffix in TIMED:
        return None
    if path.name != "localization.npz":
        return path.read_bytes()
    with np.load(path, allow_pickle=False) as archive:
        arrays = [(k, archive[k]) for k in sorted(archive.files) if k not in TIMING_ARRAYS]
    return b"".join(f"{k}{a.dtype.str}{a.shape}".encode() + a.tobytes() for k, a in arrays)


def stage_outputs(stage: str, root: Path) -> dict[str, bytes]:
    """The bytes of every file of every output listed in the stage's records, by path
    (timings left out, :func:`_comparable`)."""
    folder = stage_folder(stage, root)
    files = {}
    for record_file in stage_records(stage, root):
        record = json.loads(record_file.read_text())
        for rel in record["stage"]["outputs"]:
            path = record_file.parent / rel
            paths = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
            for p in paths:
                if (content := _comparable(stage, p)) is not None:
                    files[p.relative_to(folder).as_posix()] = content
    return files
