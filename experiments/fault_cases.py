"""Fault cases of the stages on the tiny scene: kills, corrupt files, bad configs, concurrency.

Usage:
    python experiments/fault_cases.py [--quick] [--kills 4] [--work /tmp/fault_cases]
        [--out experiments/results/fault_cases.json]

Every case runs on a fresh copy of a tiny simulated indoor dataset (the test suite's settings,
its surfel map built once) and is classified as

- ``clear``: a ``ValueError`` / ``OSError`` whose one-line message names a file of the dataset
  or the config key at fault (what ``diffloc`` prints as ``error: ...``);
- ``correct``: the stages ran and the case's own check of the result passed (a stale result
  was rebuilt, a killed run ended identical to an uninterrupted one, ...);
- ``silent``: the stages ran but the check found a wrong result;
- ``traceback``: any other exception, or a checked one whose message names neither file nor key.

Issue 17's findings 1-8 are cases ``f1_*`` ... ``f8_*``. ``--quick`` leaves out the cases that
relocalise or run many kills. ``--kills N`` sets the killed runs per kill case (SIGKILL after a
random delay, seeded; then the stage is run again and compared byte for byte). The script writes
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

from diffloc.database.database import VisualDatabase
from diffloc.io.identity import identity
from diffloc.io.lock import remove_temporaries
from diffloc.io.ply import read_point_cloud, write_point_cloud
from diffloc.maps.surfel import SurfelMapConfig
from diffloc.pipeline.build_map import BuildMapConfig, build_maps
from diffloc.pipeline.database_stage import DatabaseConfig, database_dir
from diffloc.reloc.retrieval import BowConfig, BowRetriever, load_retriever
from diffloc.sim.dataset import simulate_dataset
from tests.conftest import FINE_SURFELS, TINY, run_task, scene_config
from tests.kill_runs import killed_run, stage_folder, stage_outputs

CLASSES = ("clear", "correct", "silent", "traceback")
MAP_CFG = BuildMapConfig(point_maps=[], preview_frames=1)
KEY = re.compile(r"\b(task|db|reloc|scene|surfel)\.[a-z_0-9.]+")


class Silent(Exception):
    """The case ran to the end with a wrong result."""


def classify(root: Path, case: Callable[[Path], None]) -> tuple[str, str]:
    """Run ``case(root)``; its class and message."""
    try:
        case(root)
    except Silent as exc:
        return "silent", str(exc)
    except (ValueError, OSError) as exc:
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


def _kills(stage: str, trials: int) -> Callable[[Path], None]:
    def case(root: Path) -> None:
        # Same dataset folder name: the preview's title holds it.
        reference = root.parent.with_name(root.parent.name + "_reference") / root.name
        shutil.copytree(root, reference)
        _, work_s = killed_run(stage, reference, None)
        expected = stage_outputs(stage, reference)
        rng = random.Random(17)
        for trial in range(trials):
            (stage_folder(stage, root) / f"{stage}.json").unlink(missing_ok=True)
            killed_run(stage, root, rng.uniform(0.0, 1.1 * work_s))
            killed_run(stage, root, None)
            check(stage_outputs(stage, root) == expected, f"trial {trial}: outputs differ")
            check(remove_temporaries(stage_folder(stage, root)) == [], "temporaries left")

    case.__name__ = f"kill_{stage}_x{trials}"
    return case


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
    if not quick:
        found += [
            ("finding 2", f2_optimized_of_older_build),
            ("finding 4", f4_retriever_of_another_size),
            ("corruption", garbage_update_record),
            ("kill", _kills("build_map", kills)),
            ("kill", _kills("build_db", kills)),
        ]
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--kills", type=int, default=4)
    parser.add_argument("--work", type=Path, default=Path("/tmp/fault_cases"))
    parser.add_argument("--out", type=Path, default=Path("experiments/results/fault_cases.json"))
    args = parser.parse_args()
    shutil.rmtree(args.work, ignore_errors=True)
    base = args.work / "base" / "indoor_seed0"
    simulate_dataset(scene_config(TINY + ["scene=indoor"]), base, show_progress=False)
    build_maps(base, MAP_CFG, FINE_SURFELS, show_progress=False)
    rows = []
    for index, (group, case) in enumerate(cases(args.quick, args.kills)):
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
    counts = Counter(row["class"] for row in rows)
    summary = {
        "command": "python experiments/fault_cases.py"
        + (" --quick" if args.quick else "")
        + f" --kills {args.kills}",
        "counts": {name: counts.get(name, 0) for name in CLASSES},
        "cases": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=2) + "\n")
    lines = [
        f"`{summary['command']}`",
        "",
        "| case | group | class | message |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {r['case']} | {r['group']} | {r['class']} | {r['message'][:140].replace('|', '/')} |"
        for r in rows
    ]
    lines += ["", " / ".join(f"{name} {summary['counts'][name]}" for name in CLASSES)]
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print(summary["counts"])


if __name__ == "__main__":
    main()
