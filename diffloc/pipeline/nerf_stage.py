"""``task=train_nerf``: submaps of the mapping run and the training of one of them.

Writes ``<out_dir>/submaps.json`` and ``submaps.png`` (the clustered trajectory), and for
submap k ``submap_<k>/`` with Lightning's CSV logs and checkpoints and the exported field
(``submap_<k>/field/``: safetensors + JSON). Runs of different submaps share nothing but the
clustering, which is deterministic, so ``diffloc -m task=train_nerf nerf.submap=0,1,2,3``
trains them in parallel processes under a parallel Hydra launcher.

Each submap is a stage (:mod:`diffloc.pipeline.stage`) writing into ``submap_<k>/``: the field
and its record ``train_nerf.json`` appear together, keyed on the ``nerf`` settings and the content
of the mapping sequence, so a rerun with the same settings reuses the field and any change
trains again (resuming from the last checkpoint when ``nerf.resume``; the checkpoints are the
training's own state, kept beside the committed field).
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path

from diffloc.io.dataset import read_sequence
from diffloc.io.identity import identity
from diffloc.maps.nerf.data import build_submap_rays
from diffloc.maps.nerf.export import export_field
from diffloc.maps.nerf.submaps import cluster_trajectory, plot_submaps, save_submaps
from diffloc.maps.nerf.train import fit_submap
from diffloc.pipeline.hints import Command
from diffloc.pipeline.nerf_config import TrainNerfConfig
from diffloc.pipeline.stage import LockLevel, StageSummary, open_stage, stage_key

__all__ = ["NerfSummary", "train_nerf_submap"]


@dataclass(frozen=True)
class NerfSummary(StageSummary):
    """The ``train_nerf`` summary of one submap (``submap_<k>/train_nerf.json``).

    Attributes:
        submaps: submaps the clustering made.
        submap: the trained one.
        frames: its frames (overlap included); ``train_frames`` / ``heldout_frames`` of them
            trained on / held out for evaluation.
        steps: optimiser steps taken (over all resumed runs).
        final_loss: the last step's loss (``None`` if no step ran).
        field: path of the exported field (safetensors + JSON).
        plot: path of the clustered-trajectory plot.
    """

    submaps: int
    submap: int
    frames: int
    train_frames: int
    heldout_frames: int
    steps: int
    final_loss: float | None
    field: str
    plot: str


def train_nerf_submap(
    dataset: str | os.PathLike, config: TrainNerfConfig, show_progress: bool = True
) -> NerfSummary:
    """Cluster the mapping run and train (or resume, or reuse) one submap's field.

    Args:
        dataset: dataset folder.
        config: task settings.
        show_progress: Lightning's progress bar (off when ``CI=true``).

    Returns:
        The submap's summary (also in its record ``train_nerf.json``).

    Raises:
        ValueError: a submap index out of range, or a submap that cannot be trained (one
            frame, no lidar; see :func:`~diffloc.maps.nerf.data.build_submap_rays`).
    """
    dataset = Path(dataset)
    out_dir = Path(config.out_dir) if config.out_dir else dataset / "nerf"
    seq = read_sequence(dataset, config.sequence)
    submaps = cluster_trajectory(seq.T_wc, config.submaps)
    if not 0 <= config.submap < len(submaps):
        raise ValueError(
            f"nerf.submap={config.submap} but the clustering made {len(submaps)} submaps "
            f"(0..{len(submaps) - 1})"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    save_submaps(out_dir / "submaps.json", submaps, config.submaps)
    plot_submaps(out_dir / "submaps.png", seq.T_wc, submaps)
    submap = submaps[config.submap]
    run_dir = out_dir / f"submap_{config.submap}"
    key = stage_key(asdict(config), {"sequence": identity(dataset / config.sequence)})
    command = Command("train_nerf", (f"dataset={dataset}", f"nerf.submap={config.submap}"))
    with open_stage(run_dir, "train_nerf", command, LockLevel.DATABASE) as stage:
        if (previous := stage.reusable(key, NerfSummary)) is not None:
            return previous
        name = f"submap {config.submap} of {dataset}"
        rays = build_submap_rays(seq, submap.frames, config.data, name=name)
        module = fit_submap(
            rays, config.train, run_dir, config.epochs, config.resume, show_progress=show_progress
        )
        export_field(stage.workdir() / "field", module.field, module.grid)
        summary = NerfSummary(
            submaps=len(submaps),
            submap=config.submap,
            frames=len(submap.frames),
            train_frames=len(rays.frames),
            heldout_frames=len(rays.heldout),
            steps=module.global_step,
            final_loss=module.losses[-1] if module.losses else None,
            field=str(run_dir / "field"),
            plot=str(out_dir / "submaps.png"),
        )
        return stage.commit(key, summary, ["field"])
