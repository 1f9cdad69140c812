"""``task=train_nerf``: submaps of the mapping run and the training of one of them.

Writes ``<out_dir>/submaps.json`` and ``submaps.png`` (the clustered trajectory), and for
submap k ``submap_<k>/`` with Lightning's CSV logs and checkpoints and the exported field
(``submap_<k>/field/``: safetensors + JSON). Runs of different submaps share nothing but the
clustering, which is deterministic, so ``diffloc -m task=train_nerf nerf.submap=0,1,2,3``
trains them in parallel processes under a parallel Hydra launcher.

Each submap is a stage (:mod:`diffloc.pipeline.stage`) writing into ``submap_<k>/``: the field
and its record ``train_nerf.json`` appear together, keyed on the ``nerf`` settings and the content
of the mapping sequence, so a rerun with the same settings reuses the field and any change (or a
field changed or spoilt since its record) trains again.

The checkpoints (``checkpoints/last.ckpt``) are the training's own state, kept beside the
committed field. Each checkpoint carries the key of the training it belongs to (the stage key
without ``epochs``, ``resume`` and ``out_dir``) inside itself, under :data:`TRAINING_KEY`: the
identity is written with the weights in one file, so no kill, failed removal or copied folder
can pair a checkpoint with another training's description. With ``nerf.resume`` a run continues
from the last checkpoint only if it reads (tensors and plain values only), belongs to the same
training, holds finite weights and is not past ``nerf.epochs``; otherwise the run warns why (a
checkpoint of other settings, a spoilt one, e.g. cut short by a kill) and trains from scratch.
A training that ends with non-finite weights is refused before anything is committed.

After training, the field is scored on the submap's held-out frames
(:mod:`diffloc.pipeline.nerf_heldout`: NeRF-W PSNR, median depth and normal errors) and the
scores go into the same record (``heldout_scores``, ``heldout_note``), committed with the field.
"""

from __future__ import annotations

import os
import shutil
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import lightning as L
import torch

from diffloc.io.dataset import read_sequence
from diffloc.io.identity import identity
from diffloc.io.sequence import SequenceData
from diffloc.maps.nerf.data import SubmapRays, build_submap_rays
from diffloc.maps.nerf.export import export_field
from diffloc.maps.nerf.module import NerfModule
from diffloc.maps.nerf.submaps import Submap, cluster_trajectory, plot_submaps, save_submaps
from diffloc.maps.nerf.train import fit_submap
from diffloc.pipeline.hints import Command, StaleStageError
from diffloc.pipeline.nerf_config import TrainNerfConfig
from diffloc.pipeline.nerf_heldout import heldout_scores
from diffloc.pipeline.stage import (
    LockLevel,
    StageSummary,
    open_stage,
    output_identity,
    read_lock,
    record_path,
    stage_key,
    verified_record,
)

__all__ = [
    "TRAINING_KEY",
    "NerfSummary",
    "TrainedField",
    "cluster_mapping_run",
    "nerf_out_dir",
    "read_trained_field",
    "submap_training_data",
    "train_nerf_submap",
    "training_rays",
]


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
        heldout_scores: the field's scores on the held-out frames
            (:data:`~diffloc.pipeline.nerf_heldout.HELDOUT_KEYS`), ``None`` when no frame is
            held out.
        heldout_note: how they were taken, or why there are none.
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
    heldout_scores: dict[str, float | None] | None
    heldout_note: str


TRAINING_KEY = "diffloc_training"
"""Entry of a Lightning checkpoint holding the key of the training it belongs to."""
_NOT_TRAINING = ("epochs", "resume", "out_dir")
"""Settings that do not change what a checkpoint holds (a run may continue it)."""


class _TrainingIdentity(L.Callback):
    """Writes the training's key into every checkpoint (``checkpoint[TRAINING_KEY]``)."""

    def __init__(self, key: dict) -> None:
        self.key = key

    def on_save_checkpoint(
        self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict
    ) -> None:
        checkpoint[TRAINING_KEY] = self.key


def _unusable_checkpoint(last: Path, key: dict, max_steps: int) -> str | None:
    """Why checkpoint ``last`` cannot be resumed by the training ``key``, or ``None``."""
    try:
        state = torch.load(last, map_location="cpu", weights_only=True)
        steps, weights = int(state["global_step"]), state["state_dict"]
    except Exception as exc:  # noqa: BLE001 - any failure to read makes it unusable
        return f"it cannot be read ({type(exc).__name__}: {' '.join(str(exc).split())[:120]})"
    if TRAINING_KEY not in state:
        return "it does not say which training it belongs to (written by an older diffloc)"
    if state[TRAINING_KEY] != key:
        return "it belongs to a training of other settings or data"
    floats = [v for v in weights.values() if torch.is_tensor(v) and v.is_floating_point()]
    if not all(bool(torch.isfinite(v).all()) for v in floats):
        return "it holds non-finite weights"
    if steps > max_steps:
        return f"it is past nerf.epochs ({steps} steps, {max_steps} asked for)"
    return None


def _prepare_checkpoints(run_dir: Path, key: dict, config: TrainNerfConfig) -> bool:
    """Keep the checkpoints if ``nerf.resume`` and they can be resumed by the training ``key``
    (else remove them, warning why when there was one).

    Returns:
        Whether to resume from ``checkpoints/last.ckpt``.
    """
    last = run_dir / "checkpoints" / "last.ckpt"
    max_steps = config.epochs * config.train.steps_per_epoch
    reason = _unusable_checkpoint(last, key, max_steps) if last.is_file() else None
    if reason is not None and config.resume:
        warnings.warn(f"{last} is not resumed, training from scratch: {reason}", stacklevel=3)
    resume = config.resume and last.is_file() and reason is None
    if not resume:
        shutil.rmtree(run_dir / "checkpoints", ignore_errors=True)
    return resume


def _check_finite(module: NerfModule, name: str) -> None:
    """Refuse a trained field with non-finite weights (a diverged training).

    Raises:
        ValueError: the message names the submap and the learning-rate settings.
    """
    states = (module.field.state_dict(), module.grid.state_dict())
    values = [v for state in states for v in state.values() if v.is_floating_point()]
    if not all(bool(torch.isfinite(v).all()) for v in values):
        raise ValueError(
            f"training of {name} diverged (non-finite weights after {module.global_step} "
            "steps): lower nerf.train.lr_encoding / nerf.train.lr_network"
        )


def nerf_out_dir(dataset: Path, config: TrainNerfConfig) -> Path:
    """Where ``task=train_nerf`` writes: ``nerf.out_dir``, or ``<dataset>/nerf`` if empty."""
    return Path(config.out_dir) if config.out_dir else dataset / "nerf"


def _command(dataset: Path, submap: int) -> Command:
    """The command that trains ``submap`` (the user's ``nerf.*`` overrides replace the
    selection when the ``diffloc`` command renders it)."""
    return Command("train_nerf", (f"dataset={dataset}",), (f"nerf.submap={submap}",))


@dataclass(frozen=True)
class TrainedField:
    """A committed field as :func:`read_trained_field` read it.

    Attributes:
        files: file name -> content of the exported field folder (safetensors + JSON).
        identity: the field folder's identity recorded by its stage.
        summary: the stage's summary.
    """

    files: dict[str, bytes]
    identity: dict
    summary: NerfSummary


def read_trained_field(
    dataset: str | os.PathLike, config: TrainNerfConfig, sequence_identity: dict
) -> TrainedField:
    """The field of submap ``config.submap`` exactly as ``task=train_nerf`` with ``config``
    would reuse it, read under the submap folder's shared lock (nothing is trained).

    Args:
        dataset: dataset folder.
        config: the ``nerf`` settings; ``config.submap`` selects the submap.
        sequence_identity: identity of the mapping sequence folder (part of the key).

    Raises:
        MissingStageError: the submap was never trained; the message names the
            ``diffloc task=train_nerf ... nerf.submap=<k>`` command that trains it.
        StaleStageError: its field was trained with other ``nerf.*`` settings or data, or
            changed since; the message names the same command.
    """
    dataset = Path(dataset)
    run_dir = nerf_out_dir(dataset, config) / f"submap_{config.submap}"
    command = _command(dataset, config.submap)
    key = stage_key(asdict(config), {"sequence": sequence_identity})
    with read_lock(run_dir, LockLevel.DATABASE):
        record = verified_record(run_dir, "train_nerf", command)
        if record["stage"]["key"] != key:
            raise StaleStageError(
                f"{record_path(run_dir, 'train_nerf')} holds a field trained with other nerf.* "
                "settings or data than this run's",
                command,
            )
        files = {p.name: p.read_bytes() for p in sorted((run_dir / "field").iterdir())}
        return TrainedField(
            files, output_identity(record, "field"), NerfSummary.from_record(record)
        )


def _submap_name(dataset: str | os.PathLike, config: TrainNerfConfig) -> str:
    """How errors and warnings name the submap."""
    return f"submap {config.submap} of {dataset}"


def cluster_mapping_run(
    dataset: str | os.PathLike, config: TrainNerfConfig
) -> tuple[SequenceData, list[Submap]]:
    """The mapping run of ``dataset`` (``config.sequence``) and its submaps
    (``config.submaps``; the clustering is deterministic, so every caller gets the same).

    Raises:
        ValueError: ``config.submap`` is not one of the submaps.
    """
    seq = read_sequence(dataset, config.sequence)
    submaps = cluster_trajectory(seq.T_wc, config.submaps)
    if not 0 <= config.submap < len(submaps):
        raise ValueError(
            f"nerf.submap={config.submap} but the clustering made {len(submaps)} submaps "
            f"(0..{len(submaps) - 1})"
        )
    return seq, submaps


def training_rays(
    dataset: str | os.PathLike, seq: SequenceData, submap: Submap, config: TrainNerfConfig
) -> SubmapRays:
    """The training and held-out rays of ``submap`` as ``task=train_nerf`` builds them
    (``config.data``; the lidar rays without a return only where the empty-space loss uses
    them, ``nerf.train.loss.empty_weight > 0``)."""
    no_return = config.train.loss.empty_weight > 0
    name = _submap_name(dataset, config)
    return build_submap_rays(seq, submap.frames, config.data, name=name, no_return=no_return)


def submap_training_data(
    dataset: str | os.PathLike, config: TrainNerfConfig
) -> tuple[SequenceData, Submap, SubmapRays]:
    """The mapping run, submap ``config.submap`` and its rays, as ``task=train_nerf`` trains
    them (for scripts that train, profile or score one submap outside the task).

    Raises:
        ValueError: ``config.submap`` out of range, or a submap that cannot be trained (see
            :func:`~diffloc.maps.nerf.data.build_submap_rays`).
    """
    seq, submaps = cluster_mapping_run(dataset, config)
    submap = submaps[config.submap]
    return seq, submap, training_rays(dataset, seq, submap, config)


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
        ValueError: a submap index out of range, a submap that cannot be trained (one
            frame, no lidar; see :func:`~diffloc.maps.nerf.data.build_submap_rays`), or a
            training that diverged.
    """
    dataset = Path(dataset)
    out_dir = nerf_out_dir(dataset, config)
    seq, submaps = cluster_mapping_run(dataset, config)
    out_dir.mkdir(parents=True, exist_ok=True)
    save_submaps(out_dir / "submaps.json", submaps, config.submaps)
    plot_submaps(out_dir / "submaps.png", seq.T_wc, submaps)
    submap = submaps[config.submap]
    run_dir = out_dir / f"submap_{config.submap}"
    inputs = {"sequence": identity(dataset / config.sequence)}
    key = stage_key(asdict(config), inputs)
    training = {k: v for k, v in asdict(config).items() if k not in _NOT_TRAINING}
    command = _command(dataset, config.submap)
    with open_stage(run_dir, "train_nerf", command, LockLevel.DATABASE) as stage:
        if (previous := stage.reusable(key, NerfSummary)) is not None:
            return previous
        work = stage.workdir()  # a folder this run cannot write is refused here, before work
        rays = training_rays(dataset, seq, submap, config)
        training_key = stage_key(training, inputs)
        resume = _prepare_checkpoints(run_dir, training_key, config)
        module = fit_submap(
            rays,
            config.train,
            run_dir,
            config.epochs,
            resume,
            callbacks=[_TrainingIdentity(training_key)],
            show_progress=show_progress,
        )
        _check_finite(module, _submap_name(dataset, config))
        export_field(work / "field", module.field, module.grid)
        scores, note = heldout_scores(
            module.field, module.grid, seq, rays, config.data.holdout_every
        )
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
            heldout_scores=scores,
            heldout_note=note,
        )
        return stage.commit(key, summary, ["field"])
