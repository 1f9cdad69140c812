"""The database stages: build a visual database from a dataset, then optimise it (seed 1 III).

``build_database`` runs the surfel-aided builder over the mapping sequence. Seed 1's Table III
studies database poses with position noise: ``noise_sigma`` adds Gaussian noise (metres, per axis)
to every keyframe position before building, exactly as a badly registered database would be.
That is the simulation; what the pipeline reads is the user's belief of their pose error,
``pose_prior_sigma_m``, which sizes the builder's gates and bounds how far the optimisation may
move the poses. ``optimize_database`` then refines the keyframe poses with surfel reprojection
constraints (Eq. 1-4) and re-places the map points (Eq. 1), keeping the result only where a
check that reads neither ground truth nor the minimised cost accepts it
(:mod:`diffloc.optim.holdout`). Both write into :func:`database_dir` and report the keyframe
position RMSE against the dataset's ground truth (for scoring only), so the effect of the
optimisation is measured where it happens.

With noisy poses build with ``db.builder.association=epipolar``: the guided search of seed 1
looks for each map point around its projection at the noisy pose and makes tracks that pull the
optimisation back towards the noise (default scene, sigma 0.2 m: keyframe position RMSE 0.35 ->
0.25 m with projected tracks, -> 0.09 m with pose-independent ones).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch

from diffloc.database.builder import BuilderConfig, DatabaseBuilder
from diffloc.database.database import VisualDatabase
from diffloc.features.local import LocalFeatureConfig, XFeatConfig, make_extractor
from diffloc.io.dataset import read_sequence
from diffloc.io.identity import identity
from diffloc.maps.surfel import SurfelMap
from diffloc.optim.holdout import (
    CheckedOptimisation,
    HoldoutCheckConfig,
    checked_optimize_keyframe_poses,
)
from diffloc.optim.robust import RobustKernel
from diffloc.optim.surfel_cost import SurfelOptimConfig, replace_map_points
from diffloc.pipeline.config_record import config_record
from diffloc.pipeline.database_summary import BuiltDatabase, OptimizedDatabase
from diffloc.pipeline.hints import Command, MissingStageError
from diffloc.pipeline.stage import (
    LockLevel,
    open_stage,
    output_identity,
    read_lock,
    stage_key,
    verified_record,
)

__all__ = [
    "BUILD_STAGE",
    "OPTIMIZE_STAGE",
    "DatabaseConfig",
    "OptimisationRejectedWarning",
    "build_database",
    "database_builder",
    "database_dir",
    "database_poses",
    "db_overrides",
    "keyframe_frames",
    "keyframe_position_rmse",
    "map_command",
    "optimize_database",
    "perturb_positions",
    "read_built_record",
    "read_surfel_map",
]


@dataclass
class DatabaseConfig:
    """The visual database of a dataset (the Hydra ``db`` node).

    Attributes:
        sequence: the sequence whose images and poses make the database.
        noise_sigma: standard deviation (metres, per axis) of the Gaussian noise added to the
            keyframe positions before building (seed 1 Table III: 0, 0.2, 0.4): the
            simulation of a badly registered database, read by nothing else (the builder's
            gates follow ``pose_prior_sigma_m``).
        noise_seed: seed of that noise.
        features: the local feature extractor's settings, a
            :data:`~diffloc.features.local.LocalFeatureConfig` (XFeat, ORB, ...): its type
            picks the extractor (``features=xfeat|orb`` on the command line, whose ``_target_``
            is the class) and its ``kind`` names the database folder.
        builder: matching, fusion and culling thresholds of the builder.
        pose_prior_sigma_m: the user's belief of the per-axis position error (metres, one
            standard deviation) of the database poses, e.g. the registration accuracy of their
            mapping system. Every pose-dependent gate of the builder is sized from it, never
            from ``noise_sigma`` (the truth a real user does not know): the guided-matching
            radius and the epipolar 3D gate below. 0 (default): the poses are taken as exact,
            the builder's own floors apply. Must be finite and >= 0. Part of the database
            folder name (:func:`database_dir`).
        radius_px_per_prior_m: the guided-matching radius (``builder.association=projection``)
            grows by this many pixels per metre of ``pose_prior_sigma_m``: projected map
            points move by about ``f * error / depth`` (500 px * 0.2 m / 3 m ~ 33 px at 0.2 m
            on the default scene); 110 gives 30 px at 0.2 m and 52 px at 0.4 m on top of
            ``builder.guided_radius_px``. The guided search still centres on the wrong
            projections; with noisy poses ``builder.association=epipolar`` (pose-independent
            tracks) is the better choice.
        point_gate_m_per_prior_m: the epipolar association's 3D gate
            (``builder.epipolar.max_point_distance_m``, the floor) grows by this many metres
            per metre of ``pose_prior_sigma_m``: a true match's map point and the surfel under
            its keypoint differ by the difference of two position errors, whose norm stays
            below 4 sigma in ~97 % of cases (1.3 m at 0.2 m on top of the 0.5 m floor).
        optim: the surfel reprojection optimisation. Defaults: every keyframe free (the
            surfel planes fix the frame; the first keyframe is as noisy as the others) and a
            Cauchy kernel of 2 px: with noisy poses many associations are wrong and Huber's
            linear tail lets them outweigh the truth (on the default scene at sigma 0.2 the
            Huber cost of the true poses is higher than that of a wrong optimum).
        optim_check: the check that decides whether the optimised poses are kept
            (:mod:`diffloc.optim.holdout`): ``optim_check.accept=checked`` (default) keeps
            them only where more held-out tracks reproject within ``inlier_px`` than before
            and the keyframes moved no further than ``pose_prior_sigma_m`` makes plausible
            (``rms_move_sigmas``, ``max_move_sigmas``; so at the default prior 0 the built
            poses are kept); ``always`` keeps them regardless (the check is still run and
            reported).
    """

    sequence: str = "mapping"
    noise_sigma: float = 0.0
    noise_seed: int = 0
    features: Any = field(default_factory=lambda: XFeatConfig(max_keypoints=1000))
    builder: BuilderConfig = field(default_factory=BuilderConfig)
    pose_prior_sigma_m: float = 0.0
    radius_px_per_prior_m: float = 110.0
    point_gate_m_per_prior_m: float = 4.0
    optim: SurfelOptimConfig = field(
        default_factory=lambda: SurfelOptimConfig(
            fix_first_keyframe=False, kernel=RobustKernel("cauchy", 2.0)
        )
    )
    optim_check: HoldoutCheckConfig = field(default_factory=HoldoutCheckConfig)

    def __post_init__(self) -> None:
        if not isinstance(self.features, LocalFeatureConfig):
            raise ValueError(
                "db.features must be a local feature config (XFeatConfig, OrbConfig, SiftConfig "
                f"or AkazeConfig; on the command line features=xfeat|orb), got {self.features!r}"
            )
        prior = self.pose_prior_sigma_m
        if not _finite_at_least_zero(prior):
            raise ValueError(
                "db.pose_prior_sigma_m (the believed per-axis position error of the database "
                f"poses, metres) must be a finite number >= 0, got {prior!r}"
            )
        for name in ("noise_sigma", "radius_px_per_prior_m", "point_gate_m_per_prior_m"):
            if not _finite_at_least_zero(getattr(self, name)):
                raise ValueError(
                    f"db.{name} must be a finite number >= 0, got {getattr(self, name)!r}"
                )

    def builder_config(self) -> BuilderConfig:
        """``builder`` with its pose-dependent gates widened by ``pose_prior_sigma_m``:
        the guided-matching radius (pixels) and the epipolar 3D gate (metres, when set)."""
        prior = self.pose_prior_sigma_m
        radius = self.builder.guided_radius_px + prior * self.radius_px_per_prior_m
        epipolar = self.builder.epipolar
        if epipolar.max_point_distance_m is not None:
            gate = epipolar.max_point_distance_m + prior * self.point_gate_m_per_prior_m
            epipolar = replace(epipolar, max_point_distance_m=gate)
        return replace(self.builder, guided_radius_px=radius, epipolar=epipolar)


def _finite_at_least_zero(value: object) -> bool:
    number = isinstance(value, int | float) and not isinstance(value, bool)
    return number and math.isfinite(value) and value >= 0


def database_dir(dataset: str | Path, cfg: DatabaseConfig) -> Path:
    """``<dataset>/db/<features.kind>_sigma_<noise_sigma>_prior_<pose_prior_sigma_m>[_epipolar]``
    (e.g. ``xfeat_sigma_0.2_prior_0.4_epipolar``): where the database stages of one feature
    type, noise level, pose prior and association write."""
    suffix = "_epipolar" if cfg.builder.association == "epipolar" else ""
    name = f"{cfg.features.kind}_sigma_{cfg.noise_sigma:g}_prior_{cfg.pose_prior_sigma_m:g}"
    return Path(dataset) / "db" / f"{name}{suffix}"


def db_overrides(dataset: str | Path, db_cfg: DatabaseConfig) -> tuple[str, ...]:
    """The command-line overrides that select this dataset's database folder, for messages.

    They name every setting :func:`database_dir` reads.

    Example:
        >>> db_overrides("data/x", DatabaseConfig(noise_sigma=0.2))
        ('dataset=data/x', 'db.noise_sigma=0.2')
    """
    default = DatabaseConfig()
    words = [f"dataset={dataset}"]
    if db_cfg.noise_sigma != default.noise_sigma:
        words.append(f"db.noise_sigma={db_cfg.noise_sigma:g}")
    if db_cfg.pose_prior_sigma_m != default.pose_prior_sigma_m:
        words.append(f"db.pose_prior_sigma_m={db_cfg.pose_prior_sigma_m:g}")
    if db_cfg.features.kind != default.features.kind:
        words.append(f"features={db_cfg.features.kind}")
    if db_cfg.builder.association != default.builder.association:
        words.append(f"db.builder.association={db_cfg.builder.association}")
    return tuple(words)


def perturb_positions(T_wc: torch.Tensor, sigma: float, generator: torch.Generator) -> torch.Tensor:
    """Add N(0, sigma^2) noise to each axis of each position; rotations are kept.

    Args:
        T_wc: (N, 4, 4) camera-to-world poses.
        sigma: standard deviation in metres (>= 0).
        generator: the noise source.

    Returns:
        (N, 4, 4) perturbed poses (a copy).
    """
    if not sigma >= 0:
        raise ValueError(f"noise_sigma must be >= 0, got {sigma!r}")
    noisy = T_wc.clone()
    noise = torch.randn(T_wc.shape[0], 3, generator=generator, dtype=torch.float64)
    noisy[:, :3, 3] += sigma * noise.to(T_wc.dtype)
    return noisy


def database_poses(T_wc: torch.Tensor, cfg: DatabaseConfig) -> torch.Tensor:
    """The camera poses the database of ``cfg`` is built from: the sequence's, with its noise.

    These are the poses the pipeline has (a badly registered database's, seed 1 Table III):
    :func:`build_database` builds from them, and a later stage that needs poses besides the
    database's keyframes (the rig calibration's body trajectory) reads them here, never the
    sequence's clean poses.

    Args:
        T_wc: (N, 4, 4) camera-to-world poses of the sequence ``cfg.sequence``.
        cfg: the database settings (``noise_sigma``, ``noise_seed``).

    Returns:
        (N, 4, 4) the poses with ``N(0, noise_sigma^2)`` added to each position axis, drawn
        from ``noise_seed`` (a copy; equal to ``T_wc`` when ``noise_sigma`` is 0).

    Raises:
        ValueError: negative ``noise_sigma``.

    Example:
        >>> T = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
        >>> torch.equal(database_poses(T, DatabaseConfig()), T)
        True
    """
    return perturb_positions(T_wc, cfg.noise_sigma, torch.Generator().manual_seed(cfg.noise_seed))


def database_builder(cfg: DatabaseConfig, surfel_map: SurfelMap) -> DatabaseBuilder:
    """The builder of the database of ``cfg``: its extractor and thresholds, the guided radius
    and the epipolar 3D gate widened by the pose prior (:meth:`DatabaseConfig.builder_config`).

    Args:
        cfg: the database settings.
        surfel_map: the surfel map the keypoints are tied to.

    Returns:
        A :class:`~diffloc.database.builder.DatabaseBuilder` with an empty database.
    """
    return DatabaseBuilder(cfg.builder_config(), surfel_map, make_extractor(cfg.features))


def keyframe_position_rmse(T_wc: torch.Tensor, T_wc_true: torch.Tensor) -> float:
    """Root mean square distance (metres) between the positions of (K, 4, 4) pose sets."""
    return float((T_wc[:, :3, 3] - T_wc_true[:, :3, 3]).square().sum(-1).mean().sqrt())


def keyframe_frames(db: VisualDatabase, T_wc_built: torch.Tensor) -> torch.Tensor:
    """Frame index of every keyframe that survived culling (its pose is one of the built poses).

    Args:
        db: the built database; ``db.T_wc`` (K, 4, 4).
        T_wc_built: (N, 4, 4) the poses of the frames the database was built from.

    Returns:
        (K,) int64 frame index of each keyframe.

    Raises:
        RuntimeError: a keyframe pose matches none of ``T_wc_built``.
    """
    same = (db.T_wc[:, None] == T_wc_built[None].to(db.T_wc.dtype)).flatten(2).all(-1)
    if not bool(same.any(-1).all()):
        raise RuntimeError("a keyframe pose matches no input pose")
    return same.to(torch.int64).argmax(-1)


BUILD_STAGE = "build_db"
"""The build stage's name: its record is ``<database_dir>/build_db.json``."""
OPTIMIZE_STAGE = "optimize_db"
"""The optimisation stage's name: its record is ``<database_dir>/optimize_db.json``."""
MAP_STAGE = "build_map"
"""The map stage whose ``surfel_map.ply`` the database stages read."""


def map_command(dataset: str | Path) -> Command:
    """The command that makes the surfel map of ``dataset``."""
    return Command(MAP_STAGE, (f"dataset={dataset}",))


def read_surfel_map(dataset: str | Path) -> tuple[dict, SurfelMap]:
    """The verified ``build_map`` record and the surfel map of ``dataset``, read under the
    map folder's shared lock (a concurrent ``build_map`` cannot swap it in between).

    Raises:
        MissingStageError: no map stage record; the message names the command.
        StaleStageError: a record that does not describe the files beside it.
    """
    folder = Path(dataset) / "map"
    with read_lock(folder, LockLevel.MAP):
        record = verified_record(folder, MAP_STAGE, map_command(dataset))
        return record, SurfelMap.load(folder / "surfel_map.ply")


def read_built_record(dataset: str | Path, cfg: DatabaseConfig) -> dict:
    """The verified ``build_db`` record of the database of ``cfg``.

    Raises:
        MissingStageError: the database was not built; the message names the command.
        StaleStageError: the record does not describe the saved database (the command is named).
    """
    out = database_dir(dataset, cfg)
    return verified_record(out, BUILD_STAGE, Command(BUILD_STAGE, db_overrides(dataset, cfg)))


def build_database(
    dataset: str | Path, cfg: DatabaseConfig, show_progress: bool = True, *, rebuild: bool = False
) -> BuiltDatabase:
    """Build the visual database of ``dataset`` with ``cfg`` (module docstring).

    Needs ``<dataset>/map/surfel_map.ply`` (``diffloc task=build_map``). The stage commits as a
    whole (:mod:`diffloc.pipeline.stage`) and is reused while its configuration, the surfel map
    and the sequence folder are unchanged (``rebuild=True`` builds anyway, e.g. to time it).

    Returns:
        The summary written to ``<database_dir>/build_db.json`` (beside the stage manifest):
        statistics, the frame index of each keyframe, the keyframe position RMSE of the
        (noisy) database.

    Raises:
        MissingStageError: no surfel map (the message names the command to run).
        StaleStageError: a surfel map that its record does not describe.
        FileNotFoundError: no dataset or sequence.
    """
    root = Path(dataset)
    if not (root / "map" / f"{MAP_STAGE}.json").is_file():
        raise MissingStageError(root / "map" / f"{MAP_STAGE}.json", map_command(dataset))
    seq = read_sequence(root, cfg.sequence)
    out = database_dir(root, cfg)
    command = Command(BUILD_STAGE, db_overrides(root, cfg))
    with open_stage(out, BUILD_STAGE, command, LockLevel.DATABASE) as stage:
        map_record, surfels = read_surfel_map(root)
        inputs = {
            "surfel_map": output_identity(map_record, "surfel_map.ply"),
            "sequence": identity(root / cfg.sequence),
        }
        key = stage_key(config_record(cfg), inputs)
        previous = stage.reusable(key, BuiltDatabase)
        if previous is not None and not rebuild:
            return previous
        seq.T_wc = database_poses(seq.T_wc, cfg)
        builder = database_builder(cfg, surfels)
        db = builder.build(seq, show_progress=show_progress)
        images = len(seq.rgb_paths)
        frames = keyframe_frames(db, seq.T_wc)
        truth = read_sequence(root, cfg.sequence).T_wc[frames]  # scoring only
        db.save(stage.workdir() / "database")
        summary = BuiltDatabase(
            config=config_record(cfg),
            database=str(out / "database"),
            **db.stats(),
            keyframe_frames=frames.tolist(),
            kf_pos_rmse_m=keyframe_position_rmse(db.T_wc, truth),
            pose_prior_sigma_m=cfg.pose_prior_sigma_m,
            guided_radius_px=builder.config.guided_radius_px,
            point_gate_m=builder.config.epipolar.max_point_distance_m,
            images=images,
            features_ms_per_image=builder.timings_ms["features"] / images,
            build_ms_per_image=builder.timings_ms["database"] / images,
        )
        return stage.commit(key, summary, ["database"])


class OptimisationRejectedWarning(UserWarning):
    """The check of the surfel optimisation (held-out tracks, plausible moves) failed."""


def _check_summary(checked: CheckedOptimisation) -> dict:
    """The check's fields of :class:`OptimizedDatabase` (JSON types)."""
    return {
        "accepted": checked.accepted,
        "check_improved": checked.improved,
        "check_reason": checked.reason,
        "check_held_out_points": checked.held_out_points,
        "check_held_out_pairs": checked.before.pairs,
        "check_inlier_fraction_before": checked.before.inlier_fraction,
        "check_inlier_fraction_after": checked.after.inlier_fraction,
        "check_median_px_before": checked.before.median_px,
        "check_median_px_after": checked.after.median_px,
        "check_rms_move_m": checked.moves.rms_m,
        "check_rms_move_limit_m": checked.moves.rms_limit_m,
        "check_max_move_m": checked.moves.max_m,
        "check_max_move_limit_m": checked.moves.max_limit_m,
    }


def _warn_if_unchecked(summary: OptimizedDatabase, folder: Path) -> None:
    """Warn when the check did not vouch for the optimisation (whether it was kept or not);
    ``summary`` is the stage's, fresh or reused."""
    if summary.check_improved:
        return
    if summary.accepted:
        message = (
            f"the surfel optimisation of {folder} did not pass its check "
            f"({summary.check_reason}); its poses were kept anyway because "
            "db.optim_check.accept=always"
        )
    else:
        message = (
            f"the surfel optimisation of {folder} was not accepted ({summary.check_reason}); "
            f"{folder / 'optimized'} keeps the un-optimised poses. Force the optimised ones "
            "with db.optim_check.accept=always"
        )
    warnings.warn(message, OptimisationRejectedWarning, stacklevel=3)


def optimize_database(
    dataset: str | Path, cfg: DatabaseConfig, show_progress: bool = True, *, rebuild: bool = False
) -> OptimizedDatabase:
    """Optimise the database built with ``cfg`` by surfel reprojection, checked on held-out
    tracks (:mod:`diffloc.optim.holdout`).

    Writes ``<database_dir>/optimized``: the optimised poses if the check accepts them (or
    ``cfg.optim_check.accept="always"``), else the built poses with an
    :class:`OptimisationRejectedWarning`; either way the map points re-placed from their tracks
    at the kept poses (Eq. 1). ``optimize_db.json`` records the check
    (``accepted``, held-out inlier fractions and medians before and after, its reason), the LM
    iterations and final cost, and for scoring only the keyframe position RMSE against ground
    truth before, after (of the kept poses) and of the optimised poses whether kept or not
    (``kf_pos_rmse_optimized_m``). Ground truth is read after the decision and never by it.
    The stage commits as a whole and is reused while its configuration, the built database and
    the surfel map are unchanged (:mod:`diffloc.pipeline.stage`); ``rebuild=True`` optimises
    anyway (e.g. to time it).

    Raises:
        MissingStageError: the database or surfel map is missing (the message names the
            command to run).
        StaleStageError: a built database or surfel map that its record does not describe.
    """
    root = Path(dataset)
    out = database_dir(root, cfg)
    built_path = out / f"{BUILD_STAGE}.json"
    if not built_path.is_file():
        raise MissingStageError(built_path, Command(BUILD_STAGE, db_overrides(root, cfg)))
    command = Command(OPTIMIZE_STAGE, db_overrides(root, cfg))
    with open_stage(out, OPTIMIZE_STAGE, command, LockLevel.DATABASE) as stage:
        built = read_built_record(root, cfg)
        map_record, surfels = read_surfel_map(root)
        inputs = {
            "database": output_identity(built, "database"),
            "surfel_map": output_identity(map_record, "surfel_map.ply"),
        }
        key = stage_key(config_record(cfg), inputs)
        summary = None if rebuild else stage.reusable(key, OptimizedDatabase)
        if summary is None:
            summary = _optimize(root, cfg, built, surfels, stage.workdir())
            summary = stage.commit(key, summary, ["optimized"])
    _warn_if_unchecked(summary, out)
    return summary


def _optimize(
    root: Path, cfg: DatabaseConfig, built: dict, surfels: SurfelMap, work: Path
) -> OptimizedDatabase:
    """Optimise the built database into ``work/optimized``; the summary."""
    out = database_dir(root, cfg)
    db = VisualDatabase.load(out / "database")
    centers, normals = surfels.centers.double(), surfels.normals.double()
    T_wc_built = db.T_wc.clone()
    start = time.perf_counter()
    checked = checked_optimize_keyframe_poses(
        db, centers, normals, cfg.optim, cfg.optim_check, cfg.pose_prior_sigma_m
    )
    if checked.accepted:
        db.T_wc = checked.T_wc
    # Map points move to their tracks' surfel-plane estimate (Eq. 1) at the kept poses, the
    # built ones included: the builder creates them at surfel centres, several pixels off at
    # a few metres (on the default scene at prior 0 the relocaliser's inlier ratio falls from
    # ~0.47 to ~0.25 with the centres, and a quarter of query_same fails the ratio test).
    db.point_positions = replace_map_points(db, centers, normals)
    optimize_ms = (time.perf_counter() - start) * 1e3
    db.save(work / "optimized")
    truth = read_sequence(root, cfg.sequence).T_wc[torch.tensor(built["keyframe_frames"])]
    result = checked.result
    return OptimizedDatabase(
        config=config_record(cfg),
        database=str(out / "optimized"),
        **_check_summary(checked),
        kf_pos_rmse_before_m=keyframe_position_rmse(T_wc_built, truth),
        kf_pos_rmse_after_m=keyframe_position_rmse(db.T_wc, truth),
        kf_pos_rmse_optimized_m=keyframe_position_rmse(checked.T_wc_optimized, truth),
        iterations=int(result.iterations.max()),
        final_cost=float(result.cost.sum()),
        converged=bool(torch.as_tensor(result.converged).all()),
        optimize_ms=optimize_ms,
        optimize_ms_per_image=optimize_ms / db.num_keyframes,
    )
