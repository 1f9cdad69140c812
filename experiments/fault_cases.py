"""Fault cases of the stages on the tiny scene: kills, corrupt files, bad configs, concurrency.

Usage:
    python experiments/fault_cases.py [--quick] [--kills 4] [--work /tmp/fault_cases]
        [--out experiments/results/fault_cases.json] [--only NAME ...]

Every case runs on a fresh copy of a tiny simulated indoor dataset (the test suite's settings,
its surfel map built once) and is classified as

- ``clear``: a ``ValueError`` / ``OSError`` (or Hydra's composition error) whose one-line
  message names a file of the dataset or the config key at fault (what ``diffloc`` prints as
  ``error: ...``);
- ``correct``: the stages ran and the case's own check of the result passed (a stale result
  was rebuilt, a killed run ended identical to an uninterrupted one, ...);
- ``silent``: the stages ran but the check found a wrong result;
- ``traceback``: any other exception, or a checked one whose message names neither file nor key.

Issue 17's findings 1-8 are cases ``f1_*`` ... ``f8_*``. The other groups: ``input`` (a file a
stage reads truncated, replaced by garbage or given a NaN, for every stage and kind of file:
PLY, NPZ, JSON records, PNG images, pose tables, calibration YAML; a run that ends with the same
result as on the intact file counts as correct), ``config`` (every kind of range and name
error, which must fail before any file is written), ``concurrency`` (each pair of stages that
share a folder, run together in threads; ``stage.wait=false`` and ``stage.timeout_s``),
``read-only`` (a dataset folder that cannot be written: :mod:`tests.read_only`), ``nerf``
(checkpoints of other settings or past ``nerf.epochs``), ``kill``. ``--quick`` leaves out the
cases that relocalise and the kills of every stage but ``train_nerf`` (seconds per kill).
``--kills N`` sets the killed runs per kill case (SIGKILL after a random delay, seeded; then
the stage is run again and compared byte for byte; timings left out). ``--only`` runs the
cases whose name contains one of the given strings (to check a fix); their rows replace those
of an existing ``--out`` report, whose header then names both commands. The script writes
``--out`` (JSON: per case its group, class and message) and the same name with ``.md``
(a Markdown table and the counts per class).
"""

from __future__ import annotations

import argparse
import json
import math
import random
import re
import shutil
import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from hydra.errors import ConfigCompositionException
from safetensors.torch import load_file, save_file

from diffloc.cli import run
from diffloc.config import compose_config
from diffloc.database.database import VisualDatabase
from diffloc.eval.report_files import write_report
from diffloc.io.identity import identity
from diffloc.io.lock import LockLevel, folder_lock, remove_temporaries
from diffloc.io.ply import read_point_cloud, write_point_cloud
from diffloc.maps.nerf.export import load_field
from diffloc.maps.surfel import SurfelMapConfig
from diffloc.pipeline.build_map import BuildMapConfig, build_maps
from diffloc.pipeline.database_select import select_database
from diffloc.pipeline.database_stage import DatabaseConfig, database_dir
from diffloc.pipeline.hints import Command, StaleStageError
from diffloc.pipeline.stage import verified_record
from diffloc.reloc.retrieval import BowConfig, BowRetriever, load_retriever
from diffloc.sim.dataset import simulate_dataset
from tests.conftest import FINE_SURFELS, TINY, TINY_NERF, run_task, scene_config
from tests.kill_runs import (
    PREREQUISITES,
    folder_files,
    killed_run,
    run_stage,
    stage_outputs,
    stage_records,
    work_started,
)
from tests.read_only import read_only, snapshot

CLASSES = ("clear", "correct", "silent", "traceback")
MAP_CFG = BuildMapConfig(point_maps=[], preview_frames=1)
KEY = re.compile(
    r"\b(task|db|reloc|scene|map|nerf|stage)\.[a-z_0-9.]+"
    r"|'(features|retriever|matcher|optim|map|nerf|experiment|task|scene|reloc)/[\w/]+'"
)
"""A setting's full key (``map.voxel_size_m``) or a group option (``'features/sift'``)."""


class Silent(Exception):
    """The case ran to the end with a wrong result."""


def classify(root: Path, case: Callable[[Path], None]) -> tuple[str, str]:
    """Run ``case(root)``; its class and message."""
    try:
        case(root)
    except Silent as exc:
        return "silent", str(exc)
    except (ValueError, OSError, ConfigCompositionException) as exc:
        # Hydra's composition errors print as one line on the command line, like ours.
        message = " ".join(str(exc).split())
        named = str(root) in message or KEY.search(message) is not None
        return ("clear" if named else "traceback"), message
    except Exception as exc:  # noqa: BLE001 - every other exception is a finding
        return "traceback", "".join(traceback.format_exception_only(exc)).strip()
    return "correct", ""


def check(condition: bool, what: str) -> None:
    """Raise :class:`Silent` with ``what`` unless ``condition``."""
    if not condition:
        raise Silent(what)


def _db(root: Path, *overrides: str) -> dict:
    return run_task("build_db", root, *overrides)


# ---------------------------------------------------------------------------- findings 1-8


def f1_failed_run_then_old_config(root: Path) -> None:
    before = (root / "map" / "surfel_map.ply").read_bytes()
    image = root / "mapping" / "rgb" / "000000.png"
    good = image.read_bytes()
    image.write_bytes(b"not a png")
    try:
        run_task("build_map", root, "map.voxel_size_m=0.05", "task.point_maps=[]")
    except (ValueError, OSError):
        pass
    image.write_bytes(good)
    build_maps(root, MAP_CFG, FINE_SURFELS, False)
    check((root / "map" / "surfel_map.ply").read_bytes() == before, "map of the failed config")


def f1_render_batch_zero(root: Path) -> None:
    run_task("build_map", root, "task.render_batch=0", "map.voxel_size_m=0.05")


def f2_optimized_of_older_build(root: Path) -> None:
    noisy = ("db.noise_sigma=0.05", "db.optim.min_pairs=5", "db.optim_check.accept=always")
    _db(root, *noisy)
    run_task("optimize_db", root, *noisy)
    _db(root, *noisy, "db.noise_seed=1")
    run_task("relocalize", root, *noisy, "db.noise_seed=1", f"task.out_dir={root / 'r'}")
    raise Silent("relocalised against the optimised database of an older build")


def _nan_database(field: str) -> Callable[[Path], None]:
    def case(root: Path) -> None:
        _db(root)
        folder = database_dir(root, DatabaseConfig()) / "database"
        db = VisualDatabase.load(folder)
        getattr(db, field).view(-1)[0] = math.nan
        db.save(folder)
        VisualDatabase.load(folder)
        raise Silent(f"a database with NaN in {field} loaded")

    case.__name__ = f"f3_nan_{field}"
    return case


def f4_retriever_of_another_size(root: Path) -> None:
    _db(root)
    settings = ("retriever=bow", "reloc.database=database", "reloc.sequences=[query_same]")
    run_task("relocalize", root, *settings, f"task.out_dir={root / 'a'}")
    folder = database_dir(root, DatabaseConfig())
    db = VisualDatabase.load(folder / "database")
    slices = [db.keyframe_slice(k) for k in range(db.num_keyframes - 1)]
    BowRetriever.fit([db.descriptors[s] for s in slices], BowConfig(words=8)).save(
        folder / "retriever_bow"
    )
    run_task("relocalize", root, *settings, f"task.out_dir={root / 'b'}")
    size = load_retriever(folder / "retriever_bow").num_keyframes
    check(size == db.num_keyframes, f"a retriever of {size} keyframes used")


def f5_clouds_typo(root: Path) -> None:
    run_task("build_map", root, "task.clouds=[tls_mapp]")
    raise Silent("a map built without the misspelt cloud")


def f5_point_maps_typo(root: Path) -> None:
    run_task("build_map", root, "task.point_maps=[lidar_mapp]")
    raise Silent("no point map for the misspelt cloud, no error")


def f5_stale_point_map(root: Path) -> None:
    build_maps(root, BuildMapConfig(point_maps=["tls_map"], preview_frames=1), FINE_SURFELS, False)
    build_maps(root, MAP_CFG, FINE_SURFELS, False)
    check(not (root / "map" / "tls_point_map.ply").exists(), "a stale tls_point_map.ply stays")


def f6_ply_header_undercounts(root: Path) -> None:
    path = root / "cloud.ply"
    write_point_cloud(path, np.arange(30, dtype=np.float32).reshape(10, 3), binary=False)
    path.write_text(path.read_text().replace("element vertex 10", "element vertex 7"))
    read_point_cloud(path)
    raise Silent("an undercounting PLY header read without complaint")


def f7_recorded_frame_rate(root: Path) -> None:
    info = json.loads((root / "dataset.json").read_text())
    rates = info.get("sequence_trajectories")
    check(rates is not None, "dataset.json does not record the rates used")
    for name in info["sequences"]:
        stamps = np.loadtxt(root / name / "poses.txt", comments="#", usecols=0, ndmin=1)
        used = 1.0 / float(np.median(np.diff(stamps)))
        check(abs(rates[name]["frame_rate_hz"] - used) < 1e-6, f"{name}: recorded rate not used")


def f7_negative_frame_rate(root: Path) -> None:
    run_task("simulate", root, "scene.sequences.1.frame_rate_hz=-1", f"out_dir={root / 'x'}")
    raise Silent("a negative frame rate was simulated")


def _garbage(record: str, task: str) -> Callable[[Path], None]:
    def case(root: Path) -> None:
        _db(root)
        (root / record).write_bytes(b"\x00{not json")
        run_task(task, root)
        raise Silent(f"garbage in {record} was not noticed")

    case.__name__ = f"f8_garbage_{Path(record).stem}"
    return case


def f8_scene_voxel_negative(root: Path) -> None:
    out = root / "sim"
    try:
        run_task("simulate", root, "scene.map.voxel_size_m=-0.1", f"out_dir={out}")
    finally:
        check(not out.exists(), "a dataset was written with a negative voxel size")
    raise Silent("a negative voxel size was simulated")


def f8_reloc_max_trans_negative(root: Path) -> None:
    try:
        run_task("main", root, "reloc.max_trans_m=-0.3", f"task.out_dir={root / 'r'}")
    finally:
        check(not (root / "db").exists(), "stages ran before the range error")
    raise Silent("a negative max_trans_m was used")


def f8_temporaries_cleaned(root: Path) -> None:
    leftover = root / "map" / ".tmp-build_map-k1ll3d"
    leftover.mkdir()
    (root / "map" / ".surfel_map.ply.abc.tmp").write_bytes(b"half")
    build_maps(root, MAP_CFG, FINE_SURFELS, False)
    check(remove_temporaries(root / "map") == [], "temporaries of killed runs stay")


# ---------------------------------------------------------------------------- corruptions


def corrupt_surfel_map_then_build_db(root: Path) -> None:
    path = root / "map" / "surfel_map.ply"
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    _db(root)
    raise Silent("a database built on a truncated surfel map")


def edited_surfel_map_then_build_db(root: Path) -> None:
    _db(root)
    path = root / "map" / "surfel_map.ply"
    cloud = read_point_cloud(path)
    write_point_cloud(
        path,
        cloud.points[::2],
        cloud.normals[::2],
        extra={k: v[::2] for k, v in cloud.extra.items()},
    )
    _db(root)
    raise Silent("the database of another surfel map was reused or rebuilt silently")


def truncated_database_then_optimize(root: Path) -> None:
    _db(root)
    path = database_dir(root, DatabaseConfig()) / "database" / "arrays.npz"
    path.write_bytes(path.read_bytes()[:100])
    run_task("optimize_db", root)
    raise Silent("a truncated database was optimised")


def deleted_database_then_export(root: Path) -> None:
    _db(root)
    shutil.rmtree(database_dir(root, DatabaseConfig()) / "database")
    run_task("export_colmap", root)
    raise Silent("a missing database was exported")


def garbage_dataset_json(root: Path) -> None:
    (root / "dataset.json").write_text("{")
    run_task("build_db", root)
    raise Silent("garbage dataset.json not noticed")


def garbage_update_record(root: Path) -> None:
    _db(root)
    run_task("update_db", root, "task.sequence=query_lane")
    record = database_dir(root, DatabaseConfig()) / "updated_query_lane" / "update_db.json"
    record.write_text("[]")
    run_task("export_colmap", root, "task.database=updated_query_lane", "task.overwrite=true")
    raise Silent("garbage update record not noticed")


def unknown_sequence(root: Path) -> None:
    run_task("relocalize", root, "reloc.sequences=[query_sam]")
    raise Silent("a misspelt sequence was relocalised")


# ---------------------------------------------------------------------------- kills, concurrency


def concurrent_build_maps(root: Path) -> None:
    coarse = SurfelMapConfig(voxel_size_m=0.05, mean_radius_m=0.05, normal_radius_m=0.15)
    errors: list[BaseException] = []

    def run(surfels) -> None:
        try:
            build_maps(
                root,
                BuildMapConfig(point_maps=[], preview_frames=1, overwrite=True),
                surfels,
                False,
            )
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(s,)) for s in (coarse, FINE_SURFELS)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if errors:
        raise errors[0]
    record = json.loads((root / "map" / "build_map.json").read_text())
    digest = record["stage"]["outputs"]["surfel_map.ply"]["sha256"]
    check(identity(root / "map" / "surfel_map.ply")["sha256"] == digest, "a mixed map folder")


# ---------------------------------------------------------------------------- every stage's inputs

DB = ("db.optim.min_pairs=5", "db.optim_check.accept=always")
"""Database settings under which every database stage runs on the tiny scene."""


def _reloc_settings(root: Path) -> tuple[str, ...]:
    return (
        "retriever=bow",
        "reloc.database=database",
        "reloc.sequences=[query_same]",
        f"task.out_dir={root / 'reloc_out'}",
    )


STAGES: dict[str, Callable[[Path], object]] = {
    "build_map": lambda root: build_maps(root, MAP_CFG, FINE_SURFELS, False),
    "build_db": lambda root: run_task("build_db", root, *DB),
    "optimize_db": lambda root: run_task("optimize_db", root, *DB),
    "update_db": lambda root: run_task("update_db", root, *DB, "task.sequence=query_lane"),
    "calibrate_rig": lambda root: run_task("calibrate_rig", root, *DB),
    "relocalize": lambda root: run_task("relocalize", root, *DB, *_reloc_settings(root)),
    "export_colmap": lambda root: run_task("export_colmap", root, *DB, "task.overwrite=true"),
    "train_nerf": lambda root: run_task("train_nerf", root, *TINY_NERF),
}
"""How each stage runs in the cases below (``build_map`` as the base dataset's map)."""

NEEDS = {
    "build_map": (),
    "build_db": (),
    "optimize_db": ("build_db",),
    "update_db": ("build_db",),
    "calibrate_rig": ("build_db",),
    "relocalize": ("build_db",),
    "export_colmap": ("build_db",),
    "train_nerf": (),
}
"""The stages each stage needs to have run first."""


def _db_folder(root: Path) -> Path:
    return database_dir(root, DatabaseConfig())


def _nerf_dir(root: Path) -> Path:
    return root / "nerf" / "submap_0"


def stage_result(stage: str, root: Path) -> dict[str, bytes]:
    """What a stage made, comparable across dataset copies: its output files' bytes (for
    ``relocalize`` its metrics per sequence, for ``export_colmap`` the model's files)."""
    if stage == "relocalize":  # the metrics, not the timings
        results = json.loads((root / "reloc_out" / "results.json").read_text())
        return {
            name: json.dumps([entry[k] for k in ("queries", "recall", "mATE_m")]).encode()
            for name, entry in results["sequences"].items()
        }
    folders = {
        "build_map": (root / "map", "build_map"),
        "build_db": (_db_folder(root), "build_db"),
        "optimize_db": (_db_folder(root), "optimize_db"),
        "update_db": (_db_folder(root) / "updated_query_lane", "update_db"),
        "calibrate_rig": (_db_folder(root), "rig_calibration"),
        "train_nerf": (_nerf_dir(root), "train_nerf"),
    }
    if stage == "export_colmap":
        folder, names = _db_folder(root) / "colmap" / "database", None
    else:
        folder, record = folders[stage]
        outputs = json.loads((folder / f"{record}.json").read_text())["stage"]["outputs"]
        names = set(outputs)
    files = {}
    for path in sorted(folder.rglob("*")):
        rel = path.relative_to(folder).as_posix()
        if path.is_file() and (names is None or rel.split("/")[0] in names):
            files[rel] = path.read_bytes()
    return files


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: max(1, path.stat().st_size // 3)])


def _garbage_bytes(path: Path) -> None:
    path.write_bytes(b"\x00\xff garbage \x00" * 8)


def _nan_text(path: Path) -> None:
    """A NaN in the first data row of a text table (``poses.txt``)."""
    lines = path.read_text().splitlines(keepends=True)
    row = next(i for i, line in enumerate(lines) if line.strip() and not line.startswith("#"))
    words = lines[row].split()
    words[2] = "nan"
    lines[row] = " ".join(words) + "\n"
    path.write_text("".join(lines))


def _nan_ply(path: Path) -> None:
    """A NaN in the second coordinate of the first vertex of a binary PLY (float32 x y z)."""
    data = bytearray(path.read_bytes())
    start = data.index(b"end_header\n") + len(b"end_header\n")
    data[start + 4 : start + 8] = np.float32(np.nan).tobytes()
    path.write_bytes(bytes(data))


def _nan_npz_field(field: str) -> Callable[[Path], None]:
    def spoil(path: Path) -> None:
        with np.load(path) as archive:
            arrays = {k: archive[k] for k in archive.files}
        values = arrays[field].astype(
            np.float64 if arrays[field].dtype == np.float64 else np.float32
        )
        values.reshape(-1)[0] = np.nan
        arrays[field] = values
        np.savez(path, **arrays)

    spoil.__name__ = f"_nan_{field}"
    return spoil


def _edit_field_config(path: Path) -> None:
    """Another density bias in ``field.json``: a field that still loads, with other values."""
    record = json.loads(path.read_text())
    record["field"]["density_bias"] -= 1.0
    path.write_text(json.dumps(record, indent=1))


def _nan_safetensors(path: Path) -> None:
    """A NaN in the first floating-point tensor of a safetensors file."""
    tensors = load_file(path)
    name = next(k for k in sorted(tensors) if tensors[k].is_floating_point())
    tensors[name].view(-1)[0] = math.nan
    save_file(tensors, path)


def _nan_checkpoint(path: Path) -> None:
    """A NaN in the first floating-point weight of a Lightning checkpoint."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    weights = state["state_dict"]
    name = next(k for k in sorted(weights) if weights[k].is_floating_point())
    weights[name].view(-1)[0] = math.nan
    torch.save(state, path)


SPOILERS = {"truncated": _truncate, "garbage": _garbage_bytes, "nan": _nan_text, "nanply": _nan_ply}


def _spoilt(stage: str, rel: str | Callable[[Path], Path], how: str | Callable) -> Callable:
    """A case: run what ``stage`` needs, spoil a file it reads, run ``stage``. An error that
    names the file (or the dataset) is clear; a run that makes what the reference dataset's
    uncorrupted run made is correct (the file does not change the result); any other result
    is silent."""
    spoil = SPOILERS[how] if isinstance(how, str) else how

    def case(root: Path) -> None:
        for need in NEEDS[stage]:
            STAGES[need](root)
        path = rel(root) if callable(rel) else root / rel
        spoil(path)
        STAGES[stage](root)
        expected = stage_result(stage, REFERENCE[0])
        check(stage_result(stage, root) == expected, f"{stage} ran on a spoilt {path.name}")

    label = rel if isinstance(rel, str) else rel.__name__.strip("_")
    name = re.sub(r"[^a-z0-9]+", "_", f"{how if isinstance(how, str) else how.__name__}_{label}")
    case.__name__ = f"{stage}_{name.strip('_')}"
    return case


REFERENCE: list[Path] = []
"""The reference dataset: every stage of :data:`STAGES` run once, uncorrupted."""

FRESH: list[Path] = []
"""The tiny dataset as simulated (no stage run on it)."""


def _arrays(root: Path) -> Path:
    return _db_folder(root) / "database" / "arrays.npz"


def _db_meta(root: Path) -> Path:
    return _db_folder(root) / "database" / "database.json"


def _build_record(root: Path) -> Path:
    return _db_folder(root) / "build_db.json"


def _retriever_archive(root: Path) -> Path:
    STAGES["relocalize"](root)  # makes the cache first
    folder = _db_folder(root) / "retriever_bow"
    return next(p for p in sorted(folder.rglob("*")) if p.is_file())


def _retriever_record(root: Path) -> Path:
    STAGES["relocalize"](root)
    return _db_folder(root) / "retriever_bow.json"


def _rig_record(root: Path) -> Path:
    STAGES["calibrate_rig"](root)
    return _db_folder(root) / "rig_calibration.json"


def _field_weights(root: Path) -> Path:
    STAGES["train_nerf"](root)  # the field first
    return _nerf_dir(root) / "field" / "field.safetensors"


def _field_config(root: Path) -> Path:
    STAGES["train_nerf"](root)
    return _nerf_dir(root) / "field" / "field.json"


def _half_trained_checkpoint(root: Path) -> Path:
    """The checkpoint after the first of the two epochs (what a killed run leaves)."""
    run_task("train_nerf", root, *TINY_NERF, "nerf.epochs=1")
    return _nerf_dir(root) / "checkpoints" / "last.ckpt"


def spoilt_inputs() -> list[Callable[[Path], None]]:
    """A spoilt copy of every kind of file each stage reads."""
    return [
        # build_map: the lidar map, the mapping sequence, the dataset description
        _spoilt("build_map", "map/lidar_map.ply", "truncated"),
        _spoilt("build_map", "map/lidar_map.ply", "garbage"),
        _spoilt("build_map", "map/lidar_map.ply", "nanply"),
        _spoilt("build_map", "mapping/poses.txt", "truncated"),
        _spoilt("build_map", "mapping/poses.txt", "nan"),
        _spoilt("build_map", "mapping/calib.yaml", "garbage"),
        _spoilt("build_map", "mapping/rgb/000002.png", "truncated"),
        _spoilt("build_map", "mapping/depth/000002.png", "truncated"),
        _spoilt("build_map", "mapping/lidar/000001.ply", "truncated"),
        _spoilt("build_map", "dataset.json", "truncated"),
        # build_db: the map, its record, the mapping sequence
        _spoilt("build_db", "map/surfel_map.ply", "nanply"),
        _spoilt("build_db", "map/build_map.json", "truncated"),
        _spoilt("build_db", "mapping/rgb/000001.png", "garbage"),
        _spoilt("build_db", "mapping/poses.txt", "nan"),
        _spoilt("build_db", "mapping/calib.yaml", "truncated"),
        # optimize_db / update_db / calibrate_rig: the database and its record
        _spoilt("optimize_db", _arrays, "garbage"),
        _spoilt("optimize_db", _db_meta, "garbage"),
        _spoilt("optimize_db", _build_record, "truncated"),
        _spoilt("update_db", _arrays, "truncated"),
        _spoilt("update_db", "query_lane/rgb/000001.png", "truncated"),
        _spoilt("update_db", "query_lane/poses.txt", "garbage"),
        _spoilt("calibrate_rig", _build_record, "garbage"),
        _spoilt("calibrate_rig", "mapping/calib.yaml", "garbage"),
        _spoilt("calibrate_rig", _rig_record, "garbage"),
        # relocalize: the database, its records, the retriever cache, the queries
        _spoilt("relocalize", _arrays, _nan_npz_field("T_wc")),
        _spoilt("relocalize", _retriever_archive, "truncated"),
        _spoilt("relocalize", _retriever_record, "garbage"),
        _spoilt("relocalize", "query_same/rgb/000000.png", "truncated"),
        _spoilt("relocalize", "query_same/poses.txt", "nan"),
        _spoilt("relocalize", "query_same/calib.yaml", "garbage"),
        # export_colmap: the database, the surfel map
        _spoilt("export_colmap", _db_meta, "truncated"),
        _spoilt("export_colmap", "map/surfel_map.ply", "truncated"),
        _spoilt("export_colmap", "mapping/poses.txt", "truncated"),
        # train_nerf: its field (the run trains again), a checkpoint it resumes, its inputs
        _spoilt("train_nerf", _field_weights, "truncated"),
        _spoilt("train_nerf", _field_weights, _nan_safetensors),
        _spoilt("train_nerf", _field_config, _edit_field_config),
        _spoilt("train_nerf", _half_trained_checkpoint, "truncated"),
        _spoilt("train_nerf", _half_trained_checkpoint, "garbage"),
        _spoilt("train_nerf", _half_trained_checkpoint, _nan_checkpoint),
        _spoilt("train_nerf", "mapping/poses.txt", "nan"),
        _spoilt("train_nerf", "mapping/lidar/000001.ply", "truncated"),
        _spoilt("train_nerf", "mapping/rgb/000001.png", "garbage"),
    ]


# ---------------------------------------------------------------------------- config ranges

CONFIG_RANGES = [
    ("build_map", "task.clouds=[lidar_map,tls_map,tls_map]"),
    ("build_map", "map.voxel_size_m=-1"),
    ("build_map", "map.normal_max_nn=1"),
    ("build_map", "task.preview_frames=-1"),
    ("build_db", "db.noise_sigma=-0.1"),
    ("build_db", "db.noise_sigma=nan"),
    ("build_db", "features=sift"),
    ("build_db", "db.features.max_keypoints=0"),
    ("build_db", "db.pose_prior_sigma_m=-1"),
    ("build_db", "db.radius_px_per_prior_m=-1"),
    ("build_db", "db.point_gate_m_per_prior_m=-1"),
    ("build_db", "db.sequence=mappin"),
    ("optimize_db", "db.optim.min_pairs=-1"),
    ("optimize_db", "db.optim_check.accept=maybe"),
    ("update_db", "task.sequence=query_lan"),
    ("relocalize", "reloc.query_stride=0"),
    ("relocalize", "reloc.max_rot_deg=-5"),
    ("relocalize", "retriever=sift"),
    ("relocalize", "reloc.method.top_k=0"),
    ("relocalize", "retriever=bow reloc.retriever.words=0"),
    ("relocalize", "reloc.retriever.clusters=0"),
    ("export_colmap", "task.database=best"),
    ("train_nerf", "nerf.submap=-1"),
    ("train_nerf", "nerf.submap=7"),
    ("train_nerf", "nerf.epochs=0"),
    ("train_nerf", "nerf.sequence=mappin"),
    ("train_nerf", "nerf.train.lr_network=-0.01"),
    ("train_nerf", "nerf.train.lr_encoding=nan"),
    ("train_nerf", "nerf.train.ray_batch=0"),
    ("train_nerf", "nerf.train.normal_batch=64"),
    ("train_nerf", "nerf.train.field.encoding=voxels"),
    ("train_nerf", "nerf.train.field.triplane_resolutions=[]"),
    ("train_nerf", "nerf.train.sampler.near_m=-1"),
    ("train_nerf", "nerf.train.sampler.grid_decay=2"),
    ("train_nerf", "nerf.train.loss.depth_sigma_m=0"),
    ("train_nerf", "nerf.data.image_scale=0"),
    ("train_nerf", "nerf.data.lidar_stride=0"),
    ("train_nerf", "nerf.submaps.num_submaps=-1"),
    ("train_nerf", "nerf.submaps.position_sigma_m=0"),
    ("simulate", "scene.camera.width=0"),
    ("simulate", "scene.camera.hfov_deg=200"),
    ("simulate", "scene.trajectory.max_frames=-1"),
    ("simulate", "scene.lidar.rate_hz=0"),
    ("simulate", "scene.sensor.motion_blur_samples=0"),
    ("main", "stage.timeout_s=-1"),
    ("main", "stage.wait=maybe"),
]
"""``(task, override)``: a value out of range or a name that does not exist."""


def _config_case(task: str, override: str) -> Callable[[Path], None]:
    def case(root: Path) -> None:
        for need in NEEDS.get(task, ()):  # so the setting is the only fault
            STAGES[need](root)
        before = sorted(p.relative_to(root).as_posix() for p in root.rglob("*"))
        extra = {
            "simulate": [f"out_dir={root / 'sim'}"],
            "relocalize": [f"task.out_dir={root / 'o'}"],
            "train_nerf": TINY_NERF,  # seconds of work if the setting were let through
        }
        try:
            run_task(task, root, *DB, *extra.get(task, []), *override.split())
        finally:
            after = sorted(p.relative_to(root).as_posix() for p in root.rglob("*"))
            check(before == after, f"{task} wrote files before refusing {override}")
        raise Silent(f"{override} was accepted")

    case.__name__ = "config_" + re.sub(r"[^a-z0-9]+", "_", f"{task}_{override}").strip("_")
    return case


# ---------------------------------------------------------------------------- concurrent pairs


def _task(task: str, root: Path, *overrides: str) -> Callable[[], object]:
    """``run_task`` as a callable for a thread, its config composed here (Hydra's composition
    is not thread-safe; concurrent runs of the command are separate processes anyway)."""
    cfg = compose_config(TINY + [f"task={task}", f"dataset={root}", *overrides])
    return lambda: run(cfg)


def _together(*runs: Callable[[], object]) -> list[BaseException]:
    """Run the callables in threads started together; the exceptions they raised."""
    errors: list[BaseException] = []
    barrier = threading.Barrier(len(runs))

    def go(run: Callable[[], object]) -> None:
        barrier.wait()
        try:
            run()
        except BaseException as exc:  # noqa: BLE001 - reported to the caller
            errors.append(exc)

    threads = [threading.Thread(target=go, args=(run,)) for run in runs]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return errors


def _raise_first(errors: list[BaseException]) -> None:
    if errors:
        raise errors[0]


def concurrent_build_dbs_of_one_folder(root: Path) -> None:
    """Two seeds of the noise share the database folder: one result, whole."""
    noisy = ("db.noise_sigma=0.05", *DB)
    _raise_first(
        _together(
            _task("build_db", root, *noisy, "db.noise_seed=0"),
            _task("build_db", root, *noisy, "db.noise_seed=1"),
        )
    )
    folder = database_dir(root, DatabaseConfig(noise_sigma=0.05))
    record = verified_record(folder, "build_db", Command("build_db"))
    check(record["stage"]["key"]["config"]["noise_seed"] in (0, 1), "a mixed database folder")


def concurrent_build_map_and_build_db(root: Path) -> None:
    """build_db reads the map while build_map replaces it: the database names the map it
    was built on, and a later build_db on the new map rebuilds."""
    coarse = SurfelMapConfig(voxel_size_m=0.05, mean_radius_m=0.05, normal_radius_m=0.15)
    old = identity(root / "map" / "surfel_map.ply")
    overwrite = BuildMapConfig(point_maps=[], preview_frames=1, overwrite=True)
    _raise_first(
        _together(
            lambda: build_maps(root, overwrite, coarse, False),
            _task("build_db", root, *DB),
        )
    )
    new = identity(root / "map" / "surfel_map.ply")
    used = verified_record(_db_folder(root), "build_db", Command("x"))["stage"]["key"]["inputs"]
    check(used["surfel_map"] in (old, new), "a database of neither map")
    run_task("build_db", root, *DB)
    used = verified_record(_db_folder(root), "build_db", Command("x"))["stage"]["key"]["inputs"]
    check(used["surfel_map"] == new, "the database of the old map was reused")


def concurrent_optimize_and_build_db(root: Path) -> None:
    """optimize_db while build_db rebuilds the database: the optimised one is used only if
    made from the current build."""
    run_task("build_db", root, *DB)
    errors = _together(
        _task("optimize_db", root, *DB),
        _task("build_db", root, *DB, "db.noise_seed=3"),
    )
    _raise_first([e for e in errors if not isinstance(e, FileNotFoundError | StaleStageError)])
    try:
        selected = select_database(root, DatabaseConfig(), "optimized")
    except (FileNotFoundError, StaleStageError):
        return  # refused: made from another build, or not made
    built = verified_record(_db_folder(root), "build_db", Command("x"))
    check(
        verified_record(_db_folder(root), "optimize_db", Command("x"))["stage"]["key"]["inputs"][
            "database"
        ]
        == built["stage"]["outputs"]["database"],
        f"{selected.path} of another build was selected",
    )


def concurrent_update_and_build_db(root: Path) -> None:
    run_task("build_db", root, *DB)
    errors = _together(
        _task("update_db", root, *DB, "task.sequence=query_lane"),
        _task("build_db", root, *DB, "db.noise_seed=3"),
    )
    _raise_first([e for e in errors if not isinstance(e, FileNotFoundError | StaleStageError)])
    try:
        select_database(root, DatabaseConfig(), "updated_query_lane")
    except (FileNotFoundError, StaleStageError):
        return
    folder = _db_folder(root)
    used = verified_record(folder / "updated_query_lane", "update_db", Command("x"))
    built = verified_record(folder, "build_db", Command("x"))
    check(
        used["stage"]["key"]["inputs"]["database"] == built["stage"]["outputs"]["database"],
        "an updated database of another build was selected",
    )


def concurrent_relocalizations(root: Path) -> None:
    """Two relocalisations into one results folder (and one retriever cache)."""
    run_task("build_db", root, *DB)
    settings = _reloc_settings(root)
    _raise_first(
        _together(
            _task("relocalize", root, *DB, *settings),
            _task("relocalize", root, *DB, *settings, "reloc.max_rot_deg=10"),
        )
    )
    record = verified_record(root / "reloc_out", "relocalize", Command("x"))
    results = json.loads((root / "reloc_out" / "results.json").read_text())
    check(results["config"] == record["stage"]["key"]["config"]["reloc"], "mixed results folder")


def concurrent_simulations(root: Path) -> None:
    out = root / "sim" / "indoor_seed0"
    scene = scene_config(TINY + ["scene=indoor"])
    _raise_first(
        _together(
            lambda: simulate_dataset(scene, out, show_progress=False),
            lambda: simulate_dataset(scene, out, show_progress=False),
        )
    )
    check(folder_files(out) == folder_files(FRESH[0]), "the dataset differs from one made alone")
    names = sorted(p.name for p in out.parent.iterdir())
    check(names == [".indoor_seed0.diffloc.lock", "indoor_seed0"], "temporaries left beside it")


def _held_while(setting: str) -> Callable[[Path], None]:
    def case(root: Path) -> None:
        errors: list[BaseException] = []
        with folder_lock(root / "map", level=LockLevel.MAP):
            second = _task("build_map", root, setting)
            thread = threading.Thread(target=lambda: _collect(errors, second))
            thread.start()
            thread.join(timeout=120)
        _raise_first(errors)
        raise Silent(f"build_map ran while the map was held ({setting})")

    case.__name__ = "busy_map_" + re.sub(r"[^a-z0-9]+", "_", setting).strip("_")
    return case


def _collect(errors: list[BaseException], run: Callable[[], object]) -> None:
    try:
        run()
    except BaseException as exc:  # noqa: BLE001 - reported to the caller
        errors.append(exc)


# ---------------------------------------------------------------------------- read-only


def read_only_reuse(root: Path) -> None:
    run_task("build_db", root, *DB)
    before = snapshot(root)
    with read_only(root):
        build_maps(root, MAP_CFG, FINE_SURFELS, False)
        run_task("build_db", root, *DB)
        run_task("export_colmap", root, *DB, f"task.out_dir={root.parent / 'colmap'}")
    check(snapshot(root) == before, "the read-only dataset changed")


def read_only_build(root: Path) -> None:
    with read_only(root):
        run_task("build_db", root, *DB)
    raise Silent("a database was built in a read-only dataset")


def read_only_simulate_reuse(root: Path) -> None:
    out = FRESH[0]
    before = snapshot(out.parent)
    with read_only(out.parent):
        simulate_dataset(scene_config(TINY + ["scene=indoor"]), out, show_progress=False)
    check(snapshot(out.parent) == before, "the read-only dataset changed")


# ---------------------------------------------------------------------------- kills


KILLED = (
    "build_map",
    "build_db",
    "optimize_db",
    "update_db",
    "calibrate_rig",
    "relocalize",
    "export_colmap",
    "crossmodal_tls",
    "crossmodal_mesh",
    "crossmodal_images",
    "crossmodal_nerf",
)
"""The stages of :mod:`tests.kill_runs` killed by :func:`_kill_stage` (``simulate`` and
``train_nerf`` have cases of their own: a dataset made whole, a training resumed)."""


UNREPEATABLE = {"crossmodal_mesh": "open3d's UV atlas differs from run to run"}
"""Stages whose outputs differ between two uninterrupted runs, and why: a killed run is checked
by :func:`_check_consistent` instead of byte for byte."""


def _check_consistent(stage: str, root: Path, what: str) -> None:
    """Every record of ``stage`` describes its outputs, and one more run reuses them all (each
    stage's inputs are the current upstream outputs): a complete result of one run."""
    records = stage_records(stage, root)
    try:
        for record in records:
            verified_record(record.parent, record.stem, Command(stage))
    except StaleStageError as exc:
        raise Silent(f"{what}: {' '.join(str(exc).split())}") from exc
    before = {p: p.read_bytes() for p in records}
    killed_run(stage, root, None)
    check({p: p.read_bytes() for p in stage_records(stage, root)} == before, f"{what}: rebuilt")


def _kill_stage(stage: str, trials: int) -> Callable[[Path], None]:
    """Kills of a stage of :mod:`tests.kill_runs` (its prerequisites run first); the rerun ends
    byte-identical to an uninterrupted run (timings left out), or, for :data:`UNREPEATABLE`
    stages, with a consistent result."""

    def case(root: Path) -> None:
        reference = root.parent.with_name(root.parent.name + "_reference") / root.name
        shutil.copytree(root, reference)
        for folder in (reference, root):
            for prerequisite in PREREQUISITES.get(stage, ()):
                run_stage(prerequisite, folder)
        _, work_s = killed_run(stage, reference, None)
        expected = stage_outputs(stage, reference)
        rng = random.Random(17)
        for trial in range(trials):
            for record in stage_records(stage, root):
                record.unlink(missing_ok=True)
            killed_run(stage, root, rng.uniform(0.0, 1.1 * work_s))
            killed_run(stage, root, None)
            if stage in UNREPEATABLE:
                _check_consistent(stage, root, f"trial {trial}")
            else:
                check(stage_outputs(stage, root) == expected, f"trial {trial}: outputs differ")
            left = [p for r in stage_records(stage, root) for p in remove_temporaries(r.parent)]
            check(left == [], f"trial {trial}: temporaries left: {left}")

    case.__name__ = f"kill_{stage}_x{trials}"
    return case


def _kill_simulate(trials: int) -> Callable[[Path], None]:
    def case(root: Path) -> None:
        expected = folder_files(FRESH[0])
        rng = random.Random(5)
        _, work_s = killed_run("simulate", root.parent / "timed" / "indoor_seed0", None)
        for trial in range(trials):
            out = root.parent / f"sim{trial}" / "indoor_seed0"
            killed_run("simulate", out, rng.uniform(0.1, 0.9) * work_s)
            check(not out.exists() or folder_files(out) == expected, "a partial dataset")
            killed_run("simulate", out, None)
            check(folder_files(out) == expected, f"trial {trial}: dataset differs")
            names = sorted(p.name for p in out.parent.iterdir())
            check(names == [".indoor_seed0.diffloc.lock", "indoor_seed0"], "temporaries left")

    case.__name__ = f"kill_simulate_x{trials}"
    return case


# ---------------------------------------------------------------------------- radiance fields


def _check_field(root: Path, what: str) -> None:
    """Submap 0's field loads, its record describes it, and it is the field of an
    uninterrupted training (the reference dataset's; training is deterministic)."""
    try:
        verified_record(_nerf_dir(root), "train_nerf", Command("train_nerf"))
        load_field(_nerf_dir(root) / "field")
    except (ValueError, OSError) as exc:
        raise Silent(f"{what}: {' '.join(str(exc).split())}") from exc
    expected = stage_result("train_nerf", REFERENCE[0])
    check(stage_result("train_nerf", root) == expected, f"{what}: another field")


def nerf_checkpoint_of_other_settings(root: Path) -> None:
    """The checkpoint of a training with another learning rate is not resumed."""
    run_task("train_nerf", root, *TINY_NERF, "nerf.train.lr_network=0.001")
    STAGES["train_nerf"](root)
    _check_field(root, "the checkpoint of another learning rate was resumed")


def nerf_checkpoint_past_epochs(root: Path) -> None:
    """A run asking for fewer epochs than its checkpoint holds trains them anew."""
    STAGES["train_nerf"](root)
    summary = run_task("train_nerf", root, *TINY_NERF, "nerf.epochs=1")
    check(summary.steps == 2, f"{summary.steps} steps recorded for 1 epoch of 2 steps")
    try:
        load_field(_nerf_dir(root) / "field")
    except (ValueError, OSError) as exc:
        raise Silent(f"the field does not load: {exc}") from exc


def _kill_train_nerf(trials: int) -> Callable[[Path], None]:
    """Kills while submap 0 trains (the clock starts when its work folder appears; the first
    kill at once), each followed by a run to the end."""

    def case(root: Path) -> None:
        started = work_started("train_nerf", root)
        _, seconds = killed_run("train_nerf", root, None, after_glob=started)
        rng = random.Random(11)
        for trial in range(trials):
            shutil.rmtree(root / "nerf")
            delay = 0.0 if trial == 0 else rng.uniform(0.0, seconds)
            killed_run("train_nerf", root, delay, after_glob=started)
            if (_nerf_dir(root) / "train_nerf.json").is_file():  # finished before the kill
                _check_field(root, f"trial {trial}: a killed run's field")
            killed_run("train_nerf", root, None)
            _check_field(root, f"trial {trial}")
            check(remove_temporaries(_nerf_dir(root)) == [], f"trial {trial}: temporaries left")

    case.__name__ = f"kill_train_nerf_x{trials}"
    return case


# ---------------------------------------------------------------------------- driver


def cases(quick: bool, kills: int) -> list[tuple[str, Callable[[Path], None]]]:
    """``(group, case)`` of every case; ``quick`` leaves out relocalisation and kills."""
    found = [
        ("finding 1", f1_failed_run_then_old_config),
        ("finding 1", f1_render_batch_zero),
        ("finding 3", _nan_database("T_wc")),
        ("finding 3", _nan_database("point_positions")),
        ("finding 3", _nan_database("descriptors")),
        ("finding 5", f5_clouds_typo),
        ("finding 5", f5_point_maps_typo),
        ("finding 5", f5_stale_point_map),
        ("finding 6", f6_ply_header_undercounts),
        ("finding 7", f7_recorded_frame_rate),
        ("finding 7", f7_negative_frame_rate),
        ("finding 8", _garbage("map/build_map.json", "build_db")),
        ("finding 8", _garbage("db/xfeat_sigma_0_prior_0/build_db.json", "optimize_db")),
        ("finding 8", f8_scene_voxel_negative),
        ("finding 8", f8_reloc_max_trans_negative),
        ("finding 8", f8_temporaries_cleaned),
        ("corruption", corrupt_surfel_map_then_build_db),
        ("corruption", edited_surfel_map_then_build_db),
        ("corruption", truncated_database_then_optimize),
        ("corruption", deleted_database_then_export),
        ("corruption", garbage_dataset_json),
        ("config", unknown_sequence),
        ("concurrency", concurrent_build_maps),
    ]
    found += [("input", case) for case in spoilt_inputs() if "relocalize" not in case.__name__]
    found += [("config", _config_case(task, override)) for task, override in CONFIG_RANGES]
    found += [
        ("concurrency", concurrent_build_dbs_of_one_folder),
        ("concurrency", concurrent_build_map_and_build_db),
        ("concurrency", concurrent_optimize_and_build_db),
        ("concurrency", concurrent_update_and_build_db),
        ("concurrency", concurrent_simulations),
        ("concurrency", _held_while("stage.wait=false")),
        ("concurrency", _held_while("stage.timeout_s=0.5")),
        ("read-only", read_only_reuse),
        ("read-only", read_only_build),
        ("read-only", read_only_simulate_reuse),
        ("nerf", nerf_checkpoint_of_other_settings),
        ("nerf", nerf_checkpoint_past_epochs),
        ("kill", _kill_train_nerf(kills)),
    ]
    if not quick:
        found += [
            ("finding 2", f2_optimized_of_older_build),
            ("finding 4", f4_retriever_of_another_size),
            ("corruption", garbage_update_record),
        ]
        found += [("input", case) for case in spoilt_inputs() if "relocalize" in case.__name__]
        found += [("concurrency", concurrent_relocalizations)]
        found += [("kill", _kill_stage(stage, kills)) for stage in KILLED]
        found += [("kill", _kill_simulate(min(kills, 3)))]
    return found


def summary_markdown(summary: dict) -> str:
    """The command and the counts per class of ``summary``, then a table of the cases."""
    counts = " / ".join(f"{name} {summary['counts'][name]}" for name in CLASSES)
    lines = [
        f"`{summary['command']}`",
        *(f"then `{command}` (its cases replaced)" for command in summary.get("reruns", [])),
        "",
        f"{len(summary['cases'])} cases: {counts}",
        "",
        "| case | group | class | message |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {r['case']} | {r['group']} | {r['class']} | {r['message'][:140].replace('|', '/')} |"
        for r in summary["cases"]
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--kills", type=int, default=4)
    parser.add_argument("--work", type=Path, default=Path("/tmp/fault_cases"))
    parser.add_argument("--out", type=Path, default=Path("experiments/results/fault_cases.json"))
    parser.add_argument("--only", nargs="+", default=None, metavar="NAME")
    args = parser.parse_args()
    shutil.rmtree(args.work, ignore_errors=True)
    FRESH.append(args.work / "fresh" / "indoor_seed0")
    simulate_dataset(scene_config(TINY + ["scene=indoor"]), FRESH[0], show_progress=False)
    base = args.work / "base" / "indoor_seed0"
    shutil.copytree(FRESH[0], base)
    build_maps(base, MAP_CFG, FINE_SURFELS, show_progress=False)
    REFERENCE.append(args.work / "reference" / "indoor_seed0")
    shutil.copytree(base, REFERENCE[0])
    for stage in STAGES:
        if stage != "build_map":
            STAGES[stage](REFERENCE[0])
    rows = []
    for index, (group, case) in enumerate(cases(args.quick, args.kills)):
        if args.only and not any(name in case.__name__ for name in args.only):
            continue
        root = args.work / f"{index:02d}_{case.__name__}" / "indoor_seed0"
        shutil.copytree(base, root)
        start = time.perf_counter()
        outcome, message = classify(root, case)
        seconds = round(time.perf_counter() - start, 1)
        rows.append(
            {
                "case": case.__name__,
                "group": group,
                "class": outcome,
                "message": message.replace(str(root), "<dataset>"),
                "seconds": seconds,
            }
        )
        print(f"{case.__name__}: {outcome} ({seconds} s) {message[:160]}", flush=True)
    command = (
        "python experiments/fault_cases.py"
        + (" --quick" if args.quick else "")
        + f" --kills {args.kills}"
        + (f" --only {' '.join(args.only)}" if args.only else "")
    )
    summary = {"command": command, "reruns": [], "cases": rows}
    if args.only and args.out.is_file():  # the rerun cases replace theirs in the report
        summary = json.loads(args.out.read_text())
        summary["reruns"] = [*summary.get("reruns", []), command]
        rerun = {row["case"]: row for row in rows}
        summary["cases"] = [rerun.pop(row["case"], row) for row in summary["cases"]]
        summary["cases"] += list(rerun.values())
    counts = Counter(row["class"] for row in summary["cases"])
    summary["counts"] = {name: counts.get(name, 0) for name in CLASSES}
    write_report(args.out, summary_markdown(summary), summary)
    print(summary["counts"])


if __name__ == "__main__":
    main()
