"""``task=train_nerf``: submaps of the mapping run and the training of one of them.

Writes ``<out_dir>/submaps.json`` and ``submaps.png`` (the clustered trajectory), and for
submap k ``submap_<k>/`` with Lightning's CSV logs and checkpoints and the exported field
(``submap_<k>/field/``: safetensors + JSON). Runs of different submaps share nothing but the
clustering, which is deterministic, so ``diffloc -m task=train_nerf task.submap=0,1,2,3``
trains them in parallel processes under a parallel Hydra launcher.
"""

from __future__ import annotations

import os
from pathlib import Path

from diffloc.io.dataset import read_sequence
from diffloc.maps.nerf.data import build_submap_rays
from diffloc.maps.nerf.export import export_field
from diffloc.maps.nerf.submaps import cluster_trajectory, plot_submaps, save_submaps
from diffloc.maps.nerf.train import fit_submap
from diffloc.pipeline.nerf_config import TrainNerfTaskConfig

__all__ = ["train_nerf_submap"]


def train_nerf_submap(
    dataset: str | os.PathLike, config: TrainNerfTaskConfig, show_progress: bool = True
) -> dict:
    """Cluster the mapping run and train (or resume) one submap's field.

    Args:
        dataset: dataset folder.
        config: task settings.
        show_progress: Lightning's progress bar (off when ``CI=true``).

    Returns:
        Summary: submap count, the trained submap's frames, steps, final loss and the paths.

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
            f"task.submap={config.submap} but the clustering made {len(submaps)} submaps "
            f"(0..{len(submaps) - 1})"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    save_submaps(out_dir / "submaps.json", submaps, config.submaps)
    plot_submaps(out_dir / "submaps.png", seq.T_wc, submaps)
    submap = submaps[config.submap]
    name = f"submap {config.submap} of {dataset}"
    rays = build_submap_rays(seq, submap.frames, config.data, name=name)
    run_dir = out_dir / f"submap_{config.submap}"
    module = fit_submap(
        rays, config.train, run_dir, config.epochs, config.resume, show_progress=show_progress
    )
    field_dir = export_field(run_dir / "field", module.field, module.grid, overwrite=True)
    return {
        "submaps": len(submaps),
        "submap": config.submap,
        "frames": len(submap.frames),
        "train_frames": len(rays.frames),
        "heldout_frames": len(rays.heldout),
        "steps": module.global_step,
        "final_loss": module.losses[-1] if module.losses else None,
        "field": str(field_dir),
        "plot": str(out_dir / "submaps.png"),
    }
