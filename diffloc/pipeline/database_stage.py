"""The database stages: build a visual database from a dataset, then optimise it (seed 1 III).

``build_database`` runs the surfel-aided builder over the mapping sequence. Seed 1's Table III
studies database poses with position noise: ``noise_sigma`` adds Gaussian noise (metres, per
axis) to every keyframe position before building, exactly as a badly registered database would
be. ``optimize_database`` then refines the keyframe poses with surfel reprojection constraints
(Eq. 1-4) and re-places the map points (Eq. 1). Both write into
``<dataset>/db/sigma_<noise_sigma>/`` and report the keyframe position RMSE against the
dataset's ground truth, so the effect of the optimisation is measured where it happens.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from diffloc.database.builder import BuilderConfig, DatabaseBuilder
from diffloc.database.database import VisualDatabase
from diffloc.features.local import XFeatConfig, make_extractor
from diffloc.io.atomic import atomic_write_text
from diffloc.io.dataset import read_sequence
from diffloc.maps.surfel import SurfelMap
from diffloc.optim.robust import RobustKernel
from diffloc.optim.surfel_cost import (
    SurfelOptimConfig,
    optimize_keyframe_poses,
    replace_map_points,
)

__all__ = [
    "DatabaseConfig",
    "build_database",
    "database_dir",
    "keyframe_position_rmse",
    "optimize_database",
    "perturb_positions",
]


@dataclass
class DatabaseConfig:
    """The visual database of a dataset (the Hydra ``db`` node).

    Attributes:
        sequence: the sequence whose images and poses make the database.
        noise_sigma: standard deviation (metres, per axis) of the Gaussian noise added to the
            keyframe positions before building (seed 1 Table III: 0, 0.2, 0.4).
        noise_seed: seed of that noise.
        features: XFeat settings of the database keypoints.
        builder: matching, fusion and culling thresholds of the builder.
        optim: the surfel reprojection optimisation. Defaults: every keyframe free (the
            surfel planes fix the frame; the first keyframe is as noisy as the others) and a
            Cauchy kernel of 2 px: with noisy poses many associations are wrong and Huber's
            linear tail lets them outweigh the truth (on the default scene at sigma 0.2 the
            Huber cost of the true poses is higher than that of a wrong optimum).
    """

    sequence: str = "mapping"
    noise_sigma: float = 0.0
    noise_seed: int = 0
    features: XFeatConfig = field(default_factory=lambda: XFeatConfig(max_keypoints=1000))
    builder: BuilderConfig = field(default_factory=BuilderConfig)
    optim: SurfelOptimConfig = field(
        default_factory=lambda: SurfelOptimConfig(
            fix_first_keyframe=False, kernel=RobustKernel("cauchy", 2.0)
        )
    )


def database_dir(dataset: str | Path, noise_sigma: float) -> Path:
    """``<dataset>/db/sigma_<noise_sigma>``: where the stages of one noise level write."""
    return Path(dataset) / "db" / f"sigma_{noise_sigma:g}"


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


def keyframe_position_rmse(T_wc: torch.Tensor, T_wc_true: torch.Tensor) -> float:
    """Root mean square distance (metres) between the positions of (K, 4, 4) pose sets."""
    return float((T_wc[:, :3, 3] - T_wc_true[:, :3, 3]).square().sum(-1).mean().sqrt())


def _keyframe_frames(db: VisualDatabase, T_wc_built: torch.Tensor) -> torch.Tensor:
    """(K,) frame index of every surviving keyframe (its pose is one of the built poses)."""
    same = (db.T_wc[:, None] == T_wc_built[None].to(db.T_wc.dtype)).flatten(2).all(-1)
    if not bool(same.any(-1).all()):
        raise RuntimeError("a keyframe pose matches no input pose")
    return same.to(torch.int64).argmax(-1)


def _write_summary(path: Path, summary: dict) -> None:
    atomic_write_text(path, json.dumps(summary, indent=2) + "\n")


def build_database(dataset: str | Path, cfg: DatabaseConfig, show_progress: bool = True) -> dict:
    """Build the visual database of ``dataset`` with ``cfg`` (module docstring).

    Needs ``<dataset>/map/surfel_map.ply`` (``diffloc task=build_map``).

    Returns:
        The summary written to ``<database_dir>/build_db.json``: statistics, the frame index
        of each keyframe and the keyframe position RMSE of the (noisy) database.

    Raises:
        FileNotFoundError: no dataset, sequence or surfel map.
    """
    root = Path(dataset)
    surfel_path = root / "map" / "surfel_map.ply"
    if not surfel_path.is_file():
        raise FileNotFoundError(f"{surfel_path} is missing: run `diffloc task=build_map` first")
    seq = read_sequence(root, cfg.sequence)
    generator = torch.Generator().manual_seed(cfg.noise_seed)
    seq.T_wc = perturb_positions(seq.T_wc, cfg.noise_sigma, generator)
    builder = DatabaseBuilder(
        cfg.builder, SurfelMap.load(surfel_path), make_extractor(cfg.features)
    )
    db = builder.build(seq, show_progress=show_progress)
    frames = _keyframe_frames(db, seq.T_wc)
    truth = read_sequence(root, cfg.sequence).T_wc[frames]
    out = database_dir(root, cfg.noise_sigma)
    db.save(out / "database")
    summary = {
        "config": asdict(cfg),
        "database": str(out / "database"),
        **db.stats(),
        "keyframe_frames": frames.tolist(),
        "kf_pos_rmse_m": keyframe_position_rmse(db.T_wc, truth),
    }
    _write_summary(out / "build_db.json", summary)
    return summary


def optimize_database(dataset: str | Path, cfg: DatabaseConfig, show_progress: bool = True) -> dict:
    """Optimise the database built with ``cfg.noise_sigma`` by surfel reprojection.

    Writes ``<database_dir>/optimized`` and ``optimize_db.json`` with the keyframe position
    RMSE before and after, the LM iterations and final cost.

    Raises:
        FileNotFoundError: the database or surfel map is missing.
    """
    root = Path(dataset)
    out = database_dir(root, cfg.noise_sigma)
    built_path = out / "build_db.json"
    if not built_path.is_file():
        raise FileNotFoundError(f"{built_path} is missing: run `diffloc task=build_db` first")
    built = json.loads(built_path.read_text())
    db = VisualDatabase.load(out / "database")
    surfels = SurfelMap.load(root / "map" / "surfel_map.ply")
    centers, normals = surfels.centers.double(), surfels.normals.double()
    truth = read_sequence(root, cfg.sequence).T_wc[torch.tensor(built["keyframe_frames"])]
    before = keyframe_position_rmse(db.T_wc, truth)
    T_wc, result = optimize_keyframe_poses(db, centers, normals, cfg.optim)
    db.T_wc = T_wc
    db.point_positions = replace_map_points(db, centers, normals)
    db.save(out / "optimized")
    summary = {
        "database": str(out / "optimized"),
        "kf_pos_rmse_before_m": before,
        "kf_pos_rmse_after_m": keyframe_position_rmse(db.T_wc, truth),
        "iterations": int(result.iterations.max()),
        "final_cost": float(result.cost.sum()),
        "converged": bool(torch.as_tensor(result.converged).all()),
    }
    _write_summary(out / "optimize_db.json", summary)
    return summary
