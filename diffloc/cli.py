"""The ``diffloc`` command: one Hydra app whose ``task=`` selects the job.

Examples:
    diffloc                                         # simulate the default indoor scene
    diffloc task=simulate scene=outdoor scene.seed=3 out_dir=data/courtyard
    diffloc -m scene.seed=0,1,2                     # a multirun sweep over seeds
    diffloc task=build_map dataset=data/indoor_seed0 # surfel map + coloured point maps
    diffloc task=build_db db.noise_sigma=0.2         # visual database with noisy poses
    diffloc task=optimize_db db.noise_sigma=0.2      # surfel reprojection optimisation
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from diffloc.config import register_configs
from diffloc.pipeline.build_map import build_maps
from diffloc.pipeline.database_stage import build_database, optimize_database
from diffloc.sim.dataset import simulate_dataset

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def run_simulate(cfg: DictConfig) -> Path:
    """``task=simulate``: write (or reuse) the dataset folder ``cfg.out_dir``."""
    scene = OmegaConf.to_object(cfg.scene)
    out_dir = simulate_dataset(
        scene, Path(cfg.out_dir), overwrite=cfg.task.overwrite, show_progress=cfg.progress
    )
    print(f"dataset: {out_dir}")
    print(f"preview: {out_dir / 'preview.png'}")
    return out_dir


def run_build_map(cfg: DictConfig) -> dict:
    """``task=build_map``: surfel map, coloured point maps and preview under ``dataset/map``."""
    summary = build_maps(
        Path(cfg.dataset),
        OmegaConf.to_object(cfg.task),
        OmegaConf.to_object(cfg.surfel),
        show_progress=cfg.progress,
    )
    print(f"surfels: {summary['surfels']} from {summary['source']}")
    for key in ("surfel_map", "point_map", "tls_point_map", "preview"):
        if key in summary:
            print(f"{key}: {summary[key]}")
    return summary


def run_build_db(cfg: DictConfig) -> dict:
    """``task=build_db``: the visual database of ``dataset`` (noisy poses if ``db.noise_sigma``)."""
    summary = build_database(Path(cfg.dataset), OmegaConf.to_object(cfg.db), cfg.progress)
    print(
        f"database: {summary['database']} ({summary['keyframes']} keyframes, "
        f"{summary['map_points']} map points, keyframe position RMSE "
        f"{summary['kf_pos_rmse_m']:.3f} m)"
    )
    return summary


def run_optimize_db(cfg: DictConfig) -> dict:
    """``task=optimize_db``: surfel reprojection optimisation of the ``build_db`` database."""
    summary = optimize_database(Path(cfg.dataset), OmegaConf.to_object(cfg.db), cfg.progress)
    print(
        f"optimized: {summary['database']} (keyframe position RMSE "
        f"{summary['kf_pos_rmse_before_m']:.3f} m -> {summary['kf_pos_rmse_after_m']:.3f} m)"
    )
    return summary


TASKS: dict[str, Callable[[DictConfig], object]] = {
    "simulate": run_simulate,
    "build_map": run_build_map,
    "build_db": run_build_db,
    "optimize_db": run_optimize_db,
}


def run(cfg: DictConfig) -> object:
    """Run the task named by ``cfg.task.name`` on a composed config."""
    name = cfg.task.name
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; choose one of {sorted(TASKS)}")
    return TASKS[name](cfg)


register_configs()


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def main(cfg: DictConfig) -> None:
    """Entry point of the ``diffloc`` console script."""
    run(cfg)


if __name__ == "__main__":
    main()
