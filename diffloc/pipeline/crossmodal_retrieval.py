"""The retrieval stage of ``diffloc task=crossmodal``: NetVLAD taught by the mapping images.

``<dataset>/crossmodal/<map>/retrieval/`` (``retrieval.json``) holds ``netvlad.safetensors``:
the database's NetVLAD layer fine-tuned across the render / real-image gap
(``task.retrieval.method=finetune``,
:func:`~diffloc.crossmodal.retrieval_tuning.tune_render_retrieval`) or with a learned
whitening (``whitening``,
:func:`~diffloc.crossmodal.retrieval_whitening.whiten_render_retrieval`), and the renders'
global descriptors made with it (tensors ``netvlad.<name>`` and ``global_descriptors``). Keyed on
``task.retrieval``, the database stage's output and the mapping sequence's images, poses and
calibration; the localisation stages key on its output, so a retuned layer localises again.
Query sequences are never read here.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from safetensors.torch import load, save

from diffloc.crossmodal.database import RenderedDatabase
from diffloc.crossmodal.retrieval_tuning import RetrievalTuningConfig, tune_render_retrieval
from diffloc.crossmodal.retrieval_whitening import whiten_render_retrieval
from diffloc.features.global_ import NetVLAD
from diffloc.io.atomic import atomic_open
from diffloc.io.dataset import read_sequence
from diffloc.pipeline.crossmodal_stage import (
    MAPPING,
    RETRIEVAL_FILE,
    crossmodal_folder,
    scaled_images,
    sequence_inputs,
    stage_command,
)
from diffloc.pipeline.stage import LockLevel, StageOutcome, StageSummary, open_stage, stage_key

__all__ = ["RetrievalSummary", "tune_retrieval_stage"]

_DESCRIPTORS = "global_descriptors"


@dataclass(frozen=True)
class RetrievalSummary(StageSummary):
    """The ``retrieval`` summary: the ``method``, ``tuples`` training tuples (fine-tuning) or
    same-place pairs (whitening) from ``mapping_images`` mapping images, the fine-tuning's
    triplet loss before and after (``None`` for the whitening), the wall ``seconds``."""

    method: str
    mapping_images: int
    tuples: int
    initial_loss: float | None
    final_loss: float | None
    seconds: float


def _tensors(db: RenderedDatabase) -> dict:
    state = {f"netvlad.{k}": v.contiguous() for k, v in db.netvlad.state_dict().items()}
    return {**state, _DESCRIPTORS: db.global_descriptors.contiguous()}


def _tuned(db: RenderedDatabase, path: Path) -> RenderedDatabase:
    """``db`` with the layer and descriptors of the file ``path``."""
    tensors = load(path.read_bytes())
    projection = tensors.get("netvlad.pca_projection")
    whiten_dim = None if projection is None else projection.shape[1]
    netvlad = NetVLAD(db.netvlad.num_clusters, db.netvlad.dim, whiten_dim)
    netvlad.load_state_dict(
        {k.removeprefix("netvlad."): v for k, v in tensors.items() if k.startswith("netvlad.")}
    )
    return replace(db, netvlad=netvlad.eval(), global_descriptors=tensors[_DESCRIPTORS])


def tune_retrieval_stage(
    dataset: Path,
    option: str,
    config: RetrievalTuningConfig,
    database: tuple[RenderedDatabase, StageOutcome],
    show_progress: bool = False,
) -> tuple[RenderedDatabase, StageOutcome[RetrievalSummary]]:
    """The database with its NetVLAD tuned on the mapping images (made or reused) and the
    stage's outcome.

    Args:
        dataset: the dataset folder.
        option: the ``map`` option (the stage folder is ``<map>/retrieval``).
        config: ``task.retrieval``.
        database: the rendered database and its stage outcome.
        show_progress: progress bars.

    Raises:
        ValueError: no mapping image pairs with a render within ``task.retrieval.finetune.
            triplets`` (the message says so).
    """
    db, db_outcome = database
    folder = crossmodal_folder(dataset) / option / "retrieval"
    key = stage_key(
        {"retrieval": asdict(config)},
        {"database": db_outcome.outputs["rgbd"], **sequence_inputs(dataset, MAPPING, True)},
    )
    with open_stage(
        folder, "retrieval", stage_command(dataset, option), LockLevel.DATABASE
    ) as stage:
        summary = stage.reusable(key, RetrievalSummary)
        if summary is None:
            start = time.perf_counter()
            mapping = read_sequence(dataset, MAPPING)
            camera = mapping.camera.scaled(db.camera.width / mapping.camera.width)
            images = scaled_images(mapping, camera, list(range(len(mapping))))
            teach = (
                tune_render_retrieval if config.method == "finetune" else whiten_render_retrieval
            )
            tuned = teach(db, images, mapping.T_wc, config, show_progress=show_progress)
            result = tuned.result
            with atomic_open(stage.workdir() / RETRIEVAL_FILE, "wb") as handle:
                handle.write(save(_tensors(tuned.database)))
            summary = RetrievalSummary(
                method=config.method,
                mapping_images=tuned.mapping_images,
                tuples=tuned.pairs,
                initial_loss=None if result is None else result.initial_loss,
                final_loss=None if result is None else result.final_loss,
                seconds=round(time.perf_counter() - start, 1),
            )
            summary = stage.commit(key, summary, [RETRIEVAL_FILE])
        outcome = stage.outcome(summary)
        return _tuned(db, folder / RETRIEVAL_FILE), outcome
