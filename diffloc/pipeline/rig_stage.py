"""The rig calibration stage: the camera extrinsic (and time offset) of a built database.

Beyond seed 1 (its Sec. III-B names the lidar-camera extrinsic and time offset as where the
keyframe pose error of a lidar-posed database comes from). :func:`calibrate_database_rig` takes
the database of ``diffloc task=build_db`` (``db`` settings pick it, as for ``optimize_db``), the
body poses of its sequence at the image times and the surfel map, and runs
:func:`~diffloc.optim.rig_calibration.calibrate_rig`. The body poses are
``T_wb = T_wc T_body_camera^-1`` from ``calib.yaml`` and the camera poses the database was made
from (:func:`~diffloc.pipeline.database_stage.database_poses`: the sequence's poses with the
database's ``noise_sigma``), never the sequence's clean poses: the body twists that carry the
time offset are finite differences of the poses a user has, noise included. The stage reads
no ground truth. It writes, next to the database:

- ``rig_calibration.json``: the :class:`RigCalibrationSummary`: the correction
  ``T_correction`` (``T_body_camera <- T_body_camera @ T_correction``), its size (cm, deg),
  the time offset ``dt_s`` (image ``k`` belongs to body time ``t_k + dt``), the corrected
  ``T_body_camera``, standard deviations and the correlation of ``dt`` with the extrinsic
  (conditioning diagnostics), costs, iterations, surfel pairs and how far the correction
  moves the keyframes (``kf_pos_shift_rms_m``);
- ``rig_calibrated.urdf``: the sequence's rig URDF with the camera extrinsic corrected, when
  ``calib.yaml`` holds a URDF.

With body poses only at the image times the twists that carry the time offset are finite
differences at the image rate: on the default scene (2 Hz) ``dt`` is good to a few ms
(``experiments/bench_rig_calibration.py``); set ``task.calibration.estimate_time_offset=false``
to estimate the extrinsic alone. With per-keyframe position noise ``sigma`` (``db.noise_sigma``)
the central differences over an image interval ``h`` are off by about ``sigma sqrt(2) / (2 h)``
per axis (0.28 m/s at 0.2 m and 2 Hz, a walking speed's quarter): the time offset is then
poorly determined, and the extrinsic-only mode is likely the better choice.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from diffloc.database.database import VisualDatabase
from diffloc.geometry.rig import SensorRig
from diffloc.geometry.se3 import invert, se3_log
from diffloc.io.atomic import atomic_write_text
from diffloc.io.calib import read_calib
from diffloc.io.dataset import read_sequence
from diffloc.io.identity import identity
from diffloc.io.sequence import SequenceData
from diffloc.maps.surfel import SurfelMap
from diffloc.optim.rig_calibration import RigCalibrationConfig, calibrate_rig, corrected_rig
from diffloc.pipeline.database_stage import (
    BUILD_STAGE,
    DatabaseConfig,
    database_dir,
    database_poses,
    db_overrides,
    keyframe_position_rmse,
    read_built_record,
    read_surfel_map,
)
from diffloc.pipeline.hints import Command, MissingStageError
from diffloc.pipeline.stage import (
    LockLevel,
    StageSummary,
    open_stage,
    output_identity,
    stage_key,
)

STAGE = "rig_calibration"
"""The stage name: its record is ``<database_dir>/rig_calibration.json``."""

__all__ = ["RigCalibrationSummary", "calibrate_database_rig"]


@dataclass(frozen=True)
class RigCalibrationSummary(StageSummary):
    """The ``calibrate_rig`` summary (``rig_calibration.json``; module docstring).

    Attributes:
        config: the calibration settings.
        database: path of the database calibrated against.
        keyframes: its keyframes.
        num_pairs: surfel pairs in the cost.
        T_correction: (4, 4) the correction, ``T_body_camera <- T_body_camera @ T_correction``.
        correction_cm, correction_deg: its size.
        dt_s: the time offset (image ``k`` belongs to body time ``t_k + dt``).
        T_body_camera, T_body_camera_corrected: (4, 4) the extrinsic before and after.
        std: (6,) or (7,) standard deviations of the correction's twist ``[v, w]`` (metres,
            radians) and, when the time offset is estimated, of ``dt_s`` (seconds).
        dt_correlation: (6,) correlation of ``dt`` with the twist's components (zeros
            without a time offset).
        initial_cost, cost, iterations, converged, reason: the Gauss-Newton run.
        kf_pos_shift_rms_m: RMS of how far the correction moves the keyframes.
        calibrate_ms: wall time.
        urdf: path of ``rig_calibrated.urdf`` (``None`` when ``calib.yaml`` holds no URDF).
    """

    config: dict
    database: str
    keyframes: int
    num_pairs: int
    T_correction: list[list[float]]
    correction_cm: float
    correction_deg: float
    dt_s: float
    T_body_camera: list[list[float]]
    T_body_camera_corrected: list[list[float]]
    std: list[float]
    dt_correlation: list[float]
    initial_cost: float
    cost: float
    iterations: int
    converged: bool
    reason: str
    kf_pos_shift_rms_m: float
    calibrate_ms: float
    urdf: str | None


F64 = torch.float64


def _size(T: torch.Tensor) -> tuple[float, float]:
    """Translation (cm) and rotation angle (deg) of a (4, 4) transform."""
    return float(T[:3, 3].norm()) * 100.0, math.degrees(float(se3_log(T)[3:].norm()))


def calibrate_database_rig(
    dataset: str | Path, db_cfg: DatabaseConfig, config: RigCalibrationConfig
) -> RigCalibrationSummary:
    """Calibrate the camera extrinsic (and time offset) of the database built with ``db_cfg``.

    Args:
        dataset: the dataset folder (its surfel map and the database's sequence).
        db_cfg: the database settings (which database: :func:`database_dir`).
        config: the calibration settings.

    Returns:
        The summary written to ``<database_dir>/rig_calibration.json`` (module docstring).

    Raises:
        MissingStageError: no built database or surfel map (the message names the command).
        ValueError: the sequence's ``calib.yaml`` has no ``rig.T_body_camera`` (nothing to
            calibrate), or the errors of :func:`~diffloc.optim.rig_calibration.calibrate_rig`.
    """
    root = Path(dataset)
    seq = read_sequence(root, db_cfg.sequence)
    if seq.T_body_camera is None:
        raise ValueError(
            f"{root / db_cfg.sequence / 'calib.yaml'} has no rig.T_body_camera: the rig "
            "calibration corrects that extrinsic, so the sequence must state it"
        )
    out = database_dir(root, db_cfg)
    built_path = out / f"{BUILD_STAGE}.json"
    if not built_path.is_file():
        raise MissingStageError(built_path, Command(BUILD_STAGE, db_overrides(root, db_cfg)))
    command = Command("calibrate_rig", db_overrides(root, db_cfg))
    with open_stage(out, STAGE, command, LockLevel.DATABASE) as stage:
        built = read_built_record(root, db_cfg)
        map_record, surfels = read_surfel_map(root)
        inputs = {
            "database": output_identity(built, "database"),
            "surfel_map": output_identity(map_record, "surfel_map.ply"),
            "sequence": identity(root / db_cfg.sequence),
        }
        key = stage_key(asdict(config), inputs)
        previous = stage.reusable(key, RigCalibrationSummary)
        if previous is not None:
            return previous
        summary = _calibrate(root, db_cfg, config, built, surfels, seq, stage.workdir())
        outputs = [] if summary.urdf is None else ["rig_calibrated.urdf"]
        return stage.commit(key, summary, outputs, ["rig_calibrated.urdf"])


def _calibrate(
    root: Path,
    db_cfg: DatabaseConfig,
    config: RigCalibrationConfig,
    built: dict,
    surfels: SurfelMap,
    seq: SequenceData,
    work: Path,
) -> RigCalibrationSummary:
    """Run the calibration; write the corrected URDF (if any) into ``work``; the summary."""
    out = database_dir(root, db_cfg)
    frames = torch.tensor(built["keyframe_frames"], dtype=torch.int64)
    db = VisualDatabase.load(out / "database")
    T_bc = seq.T_body_camera.to(F64)
    # The body trajectory of the poses the database was built from (noise included).
    T_wb = database_poses(seq.T_wc, db_cfg).to(F64) @ invert(T_bc)
    times = torch.as_tensor(seq.timestamps, dtype=F64)
    start = time.perf_counter()
    fit = calibrate_rig(
        db, surfels.centers.to(F64), surfels.normals.to(F64), T_wb, times, frames, config
    )
    elapsed_ms = (time.perf_counter() - start) * 1e3
    size_cm, size_deg = _size(fit.T_correction)
    urdf = read_calib(root / db_cfg.sequence / "calib.yaml").rig_urdf
    if urdf is not None:
        rig = corrected_rig(SensorRig.from_urdf(urdf), fit.T_correction)
        atomic_write_text(work / "rig_calibrated.urdf", rig.to_urdf())
    return RigCalibrationSummary(
        config=asdict(config),
        database=str(out / "database"),
        keyframes=db.num_keyframes,
        num_pairs=fit.num_pairs,
        T_correction=fit.T_correction.tolist(),
        correction_cm=size_cm,
        correction_deg=size_deg,
        dt_s=fit.dt,
        T_body_camera=T_bc.tolist(),
        T_body_camera_corrected=(T_bc @ fit.T_correction).tolist(),
        std=fit.std.tolist(),
        dt_correlation=fit.dt_correlation.tolist(),
        initial_cost=fit.initial_cost,
        cost=fit.cost,
        iterations=fit.iterations,
        converged=fit.converged,
        reason=fit.reason,
        kf_pos_shift_rms_m=keyframe_position_rmse(fit.T_wc, db.T_wc),
        calibrate_ms=elapsed_ms,
        urdf=None if urdf is None else str(out / "rig_calibrated.urdf"),
    )
