"""The database stage of ``diffloc task=crossmodal map=hybrid``: real images plus the renders
no real image covers (beyond seed 2).

The two parts are the databases of ``map=images`` (:mod:`diffloc.pipeline.crossmodal_images`)
and ``map=mesh`` (:func:`~diffloc.pipeline.crossmodal_stage.build_rgbd_database`), made or
reused by their own stages. This stage ``<dataset>/crossmodal/hybrid/database/``
(``rgbd_database.json``) keeps every real image and the renders
:func:`~diffloc.crossmodal.hybrid.uncovered_views` finds uncovered, and builds XFeat features
and one NetVLAD over the union (``rgbd/``): the global descriptors of real and rendered images
must come from the same layer to be ranked together. The database marks its real images
(:attr:`~diffloc.crossmodal.database.RenderedDatabase.real`), so a pose from one is held to
the real images' photometric threshold. Keyed on the coverage bounds,
``task.database`` and the two parts' outputs.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from diffloc.crossmodal.database import DatabaseConfig, RenderedDatabase, build_database
from diffloc.crossmodal.hybrid import uncovered_views
from diffloc.crossmodal.synthesize import RGBD
from diffloc.pipeline.crossmodal_config import HybridMapConfig
from diffloc.pipeline.crossmodal_stage import camera_settings, crossmodal_folder, stage_command
from diffloc.pipeline.stage import LockLevel, StageOutcome, StageSummary, open_stage, stage_key

__all__ = ["HybridDatabaseSummary", "build_hybrid_database"]


@dataclass(frozen=True)
class HybridDatabaseSummary(StageSummary):
    """The ``rgbd_database`` summary of ``map=hybrid``: ``real_images`` mapping frames and
    ``rendered_images`` of ``renders`` mesh renders (the uncovered ones), ``images`` in all,
    and their share of pixels without depth (``hole_share``)."""

    images: int
    real_images: int
    rendered_images: int
    renders: int
    hole_share: float


def build_hybrid_database(
    dataset: Path,
    config: HybridMapConfig,
    database: DatabaseConfig,
    real: tuple[RenderedDatabase, StageOutcome],
    rendered: tuple[RenderedDatabase, StageOutcome],
    show_progress: bool = False,
) -> tuple[RenderedDatabase, StageOutcome[HybridDatabaseSummary]]:
    """The hybrid RGB-D database (made or reused) and the stage's outcome.

    Args:
        dataset: the dataset folder.
        config: the ``map=hybrid`` node.
        database: features and NetVLAD settings (``task.database``).
        real: the real-image database of the mapping frames and its outcome.
        rendered: the mesh's rendered database and its outcome (same camera).
        show_progress: progress bars.

    Returns:
        The database (the real images first, then the uncovered renders in render order) and
        the outcome, whose output ``rgbd`` keys the localisation stages.

    Raises:
        ValueError: the two parts have different cameras.
    """
    (real_db, real_outcome), (render_db, render_outcome) = real, rendered
    if camera_settings(real_db.camera) != camera_settings(render_db.camera):
        raise ValueError(
            "map=hybrid: the real-image and rendered databases have different cameras "
            f"({camera_settings(real_db.camera)} vs {camera_settings(render_db.camera)})"
        )
    folder = crossmodal_folder(dataset) / "hybrid" / "database"
    coverage = {"max_distance_m": config.max_distance_m, "max_angle_deg": config.max_angle_deg}
    key = stage_key(
        {"coverage": coverage, "database": asdict(database)},
        {"real": real_outcome.outputs["rgbd"], "rendered": render_outcome.outputs["rgbd"]},
    )
    with open_stage(
        folder, "rgbd_database", stage_command(dataset, "hybrid"), LockLevel.DATABASE
    ) as stage:
        summary = stage.reusable(key, HybridDatabaseSummary)
        if summary is None:
            keep = uncovered_views(render_db.T_wc, real_db.T_wc, **coverage)
            views = RGBD(
                torch.cat([real_db.rgb, render_db.rgb[keep]]),
                torch.cat([real_db.depth, render_db.depth[keep]]),
            )
            T_wc = torch.cat([real_db.T_wc, render_db.T_wc[keep]])
            source = f"{real_db.source} + {int(keep.sum())} uncovered {render_db.source} renders"
            real = torch.arange(len(T_wc)) < real_db.num_images
            db = build_database(
                views,
                T_wc,
                real_db.camera,
                database,
                source,
                show_progress=show_progress,
                real=real,
            )
            db.save(stage.workdir() / "rgbd")
            summary = HybridDatabaseSummary(
                images=db.num_images,
                real_images=real_db.num_images,
                rendered_images=int(keep.sum()),
                renders=render_db.num_images,
                hole_share=float(db.holes.mean()),
            )
            summary = stage.commit(key, summary, ["rgbd"])
        outcome = stage.outcome(summary)
        return RenderedDatabase.load(folder / "rgbd"), outcome
