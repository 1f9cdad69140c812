"""Held-out scores of a trained submap field for the ``train_nerf`` record.

``task=train_nerf`` holds out every ``nerf.data.holdout_every``-th mapping frame of the submap
(:func:`~diffloc.maps.nerf.data.split_frames`) and, after training, scores the field on them
with the benchmark's protocol (:func:`~diffloc.eval.field_scores.heldout_field_scores`, at
the training resolution): the appearance code fitted on the left half of each image (field
frozen), PSNR on the right half, as NeRF-W does; median depth and normal errors against the
sequence's depth images when it has them. Scoring only: nothing here changes the field or
feeds the pipeline.
"""

from __future__ import annotations

from diffloc.eval.field_scores import heldout_field_scores
from diffloc.io.sequence import SequenceData
from diffloc.maps.nerf.data import SubmapRays
from diffloc.maps.nerf.field import RadianceField
from diffloc.maps.nerf.sampler import DensityGrid

__all__ = ["HELDOUT_KEYS", "heldout_line", "heldout_scores"]

HELDOUT_KEYS = ("psnr_heldout_db", "depth_median_abs_err_m", "normal_median_err_deg")
"""The scores of the record, in :func:`~diffloc.eval.field_scores.heldout_field_scores`'s names."""

_PROTOCOL = (
    "mean over {n} held-out frame(s) at {w}x{h}: appearance code fitted on the left half of "
    "each image (field frozen), PSNR on the right half (NeRF-W); "
)


def heldout_scores(
    field: RadianceField,
    grid: DensityGrid,
    seq: SequenceData,
    rays: SubmapRays,
    holdout_every: int,
) -> tuple[dict[str, float | None] | None, str]:
    """Score a trained field on its submap's held-out frames.

    Args:
        field: the trained field (left unchanged).
        grid: its density grid (left unchanged).
        seq: the mapping sequence the submap was trained on.
        rays: the submap's rays (``rays.heldout`` the held-out frames, ``rays.camera`` the
            training resolution); without held-out frames nothing is scored.
        holdout_every: ``nerf.data.holdout_every`` (named in the note when nothing is held out).

    Returns:
        ``(scores, note)``: ``scores`` maps :data:`HELDOUT_KEYS` to values (the depth and
        normal errors ``None`` when the sequence has no depth images), or is ``None`` when no
        frame is held out; ``note`` says how the scores were taken, or why there are none.
    """
    if not rays.heldout:
        if holdout_every == 0:
            return None, "not scored: nerf.data.holdout_every=0 holds out no frame"
        return None, (
            "not scored: no frame index of the submap is a multiple of "
            f"nerf.data.holdout_every={holdout_every}"
        )
    full = seq.depth_paths is not None
    raw = heldout_field_scores(field, grid, seq, rays.camera, rays.heldout, full)
    scores = {key: raw.get(key) for key in HELDOUT_KEYS}
    cam = rays.camera
    note = _PROTOCOL.format(n=len(rays.heldout), w=cam.width, h=cam.height)
    if full:
        note += "depth and normal errors against the sequence's depth images (scoring only)"
    else:
        note += f"no depth or normal error: sequence {seq.name!r} has no depth images"
    return scores, note


def heldout_line(scores: dict[str, float | None] | None, note: str) -> str:
    """One line for the terminal: the scores of :func:`heldout_scores`, or why there are none.

    Example:
        >>> keys = ("psnr_heldout_db", "depth_median_abs_err_m", "normal_median_err_deg")
        >>> heldout_line(dict(zip(keys, (24.31, 0.0512, 9.87))), "...")
        'held-out: PSNR 24.31 dB, median depth error 0.051 m, median normal error 9.9 deg'
        >>> heldout_line(dict(zip(keys, (24.31, None, None))), "...")
        'held-out: PSNR 24.31 dB, median depth error n/a, median normal error n/a'
        >>> heldout_line(None, "not scored: nerf.data.holdout_every=0 holds out no frame")
        'held-out: not scored: nerf.data.holdout_every=0 holds out no frame'
    """
    if scores is None:
        return f"held-out: {note}"
    depth, normal = scores["depth_median_abs_err_m"], scores["normal_median_err_deg"]
    return (
        f"held-out: PSNR {scores['psnr_heldout_db']:.2f} dB, median depth error "
        + ("n/a" if depth is None else f"{depth:.3f} m")
        + ", median normal error "
        + ("n/a" if normal is None else f"{normal:.1f} deg")
    )
