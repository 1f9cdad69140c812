"""A recorded localisation of a query sequence for tests: the fields a test does not set are
neutral (identity poses, nothing found or accepted, no candidates)."""

from __future__ import annotations

import numpy as np

from diffloc.pipeline.crossmodal_stage import SequenceLocalization, candidate_arrays
from diffloc.reloc.stage_clock import STAGES


def sequence_localization(q: int, **fields: np.ndarray) -> SequenceLocalization:
    """A :class:`SequenceLocalization` of ``q`` queries with ``fields`` (arrays of length
    ``q``, or the candidate arrays of :func:`candidate_arrays`) replacing the neutral ones."""
    zeros, flags = np.zeros(q, dtype=np.int64), np.zeros(q, dtype=bool)
    neutral = {
        "frames": np.arange(q),
        "T_wc": np.tile(np.eye(4), (q, 1, 1)),
        "success": flags,
        "accepted": flags,
        "reference": zeros,
        "top1": zeros,
        "num_matches": zeros,
        "num_points": zeros,
        "num_inliers": zeros,
        "photometric": np.full(q, 0.5),
        "accepted_without_photometric": flags,
        "from_prior": flags,
        "prior_images": zeros,
        "time_ms": np.ones(q),
        "cpu_ms": np.ones(q),
        "stage_ms": np.zeros((q, len(STAGES))),
        "stage_cpu_ms": np.zeros((q, len(STAGES))),
        **candidate_arrays([]),
    }
    return SequenceLocalization(**{**neutral, **fields})
