"""Learning curves (a score measured at increasing times): when a curve first reaches a level.

Used to compare training runs at a fixed quality, e.g. the CPU seconds each radiance-field
sampler needs to reach a held-out PSNR (``experiments/bench_nerf.py``).

Example:
    >>> time_to_reach([30.0, 60.0, 90.0], [20.0, 22.0, 23.0], 21.0)
    45.0
    >>> common_level({"a": [20.0, 23.0], "b": [19.0, 22.5]})
    22.5
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

__all__ = ["common_level", "time_to_reach"]


def time_to_reach(times: Sequence[float], scores: Sequence[float], level: float) -> float | None:
    """First time a curve reaches ``level``, by linear interpolation between the measurement
    before the first one at or above the level and that one.

    Args:
        times: (N,) increasing measurement times.
        scores: (N,) scores at those times.
        level: the score to reach.

    Returns:
        The interpolated time; the first time when the first score is already at or above the
        level; ``None`` when no score reaches it.
    """
    if len(times) != len(scores):
        raise ValueError(f"times ({len(times)}) and scores ({len(scores)}) differ in length")
    if any(b <= a for a, b in zip(times, times[1:], strict=False)):
        raise ValueError("times must be strictly increasing")
    for i, (t, s) in enumerate(zip(times, scores, strict=True)):
        if s >= level:
            if i == 0:
                return float(t)
            t0, s0 = times[i - 1], scores[i - 1]
            return float(t0 + (level - s0) / (s - s0) * (t - t0))
    return None


def common_level(curves: Mapping[str, Sequence[float]]) -> float:
    """The highest score every curve reaches: the smallest of the curves' best scores.

    Args:
        curves: name -> (N_name,) scores, each non-empty.

    Returns:
        ``min over curves of max score``.
    """
    empty = [name for name, scores in curves.items() if len(scores) == 0]
    if not curves or empty:
        raise ValueError(f"every curve needs a score; empty: {empty or 'no curves given'}")
    return float(min(max(scores) for scores in curves.values()))
