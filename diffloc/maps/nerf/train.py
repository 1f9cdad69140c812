"""Fit one submap's field with a CPU ``lightning.Trainer``: CSV logs, end-of-epoch
checkpoints, resumption, export."""

from __future__ import annotations

import os
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger

from diffloc.maps.nerf.data import SubmapRays
from diffloc.maps.nerf.module import NerfDataModule, NerfModule, NerfTrainConfig
from diffloc.progress import progress_enabled

__all__ = ["fit_submap", "load_checkpoint"]


def fit_submap(
    rays: SubmapRays,
    config: NerfTrainConfig,
    out_dir: str | os.PathLike,
    epochs: int,
    resume: bool = False,
    callbacks: list[L.Callback] | tuple = (),
    show_progress: bool = True,
) -> NerfModule:
    """Train (or continue training) a submap's field.

    Args:
        rays: the submap's training rays.
        config: training settings.
        out_dir: run folder: ``logs/`` (CSV), ``checkpoints/`` (``last.ckpt`` each epoch).
        epochs: train until this many epochs of ``config.steps_per_epoch`` steps are done.
        resume: continue from ``checkpoints/last.ckpt`` if it exists (read with
            ``weights_only``: tensors and plain values, no pickled objects).
        callbacks: extra Lightning callbacks (e.g. evaluation in a benchmark).
        show_progress: Lightning's progress bar (off when ``CI=true``).

    Returns:
        The trained module.
    """
    out_dir = Path(out_dir)
    module = NerfModule(config, rays.box_min, rays.box_max, len(rays.frames))
    checkpoint = ModelCheckpoint(
        dirpath=out_dir / "checkpoints", save_last=True, save_top_k=0, every_n_epochs=1
    )
    trainer = L.Trainer(
        accelerator="cpu",
        devices=1,
        max_epochs=epochs,
        logger=CSVLogger(out_dir, name="logs", version=0, flush_logs_every_n_steps=10),
        callbacks=[checkpoint, *callbacks],
        enable_model_summary=False,
        enable_progress_bar=progress_enabled(show_progress),
        num_sanity_val_steps=0,
        log_every_n_steps=1,
        deterministic=False,
    )
    last = out_dir / "checkpoints" / "last.ckpt"
    ckpt_path = str(last) if resume and last.is_file() else None
    trainer.fit(module, NerfDataModule(rays, config), ckpt_path=ckpt_path, weights_only=True)
    return module


def load_checkpoint(
    rays: SubmapRays, config: NerfTrainConfig, path: str | os.PathLike
) -> tuple[NerfModule, int]:
    """The module of a training checkpoint (e.g. ``checkpoints/last.ckpt`` of
    :func:`fit_submap`), read with ``weights_only`` (no pickled objects), and its step.

    Args:
        rays: the submap's training rays (they size the box and the appearance codes).
        config: the training settings the checkpoint was made with.
        path: the checkpoint file.

    Returns:
        ``(module, step)``: the module with the checkpoint's weights and its global step.
    """
    module = NerfModule(config, rays.box_min, rays.box_max, len(rays.frames))
    state = torch.load(path, map_location="cpu", weights_only=True)
    module.load_state_dict(state["state_dict"])
    return module, int(state["global_step"])
