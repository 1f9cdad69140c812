"""Wall and CPU time per stage of one localisation query.

The rendered-database localiser (:mod:`diffloc.reloc.rendered`) times each of its stages with
one :class:`StageClock` per query; a stage entered several times (LighterGlue and PnP once
per candidate) adds up. CPU time is the process's (``time.process_time``: every thread), so
with one thread (``OMP_NUM_THREADS=1``) it is the work done, while wall time also holds the
waits of a loaded machine.

Example:
    >>> clock = StageClock()
    >>> with clock.measure("matching") as lap:
    ...     _ = sum(range(1000))
    >>> lap.wall_ms >= 0.0, clock.wall_ms["matching"] == lap.wall_ms, clock.wall_ms["pnp"]
    (True, True, 0.0)
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

__all__ = ["STAGES", "Lap", "StageClock"]

STAGES = ("features", "retrieval", "rerank", "matching", "pnp", "photometric")
"""The timed stages of a query: XFeat keypoints and dense map, the global descriptor and its
search, the mutual-nearest-neighbour re-ranking, LighterGlue (every candidate), lifting + PnP
RANSAC + refinement (every candidate), and the photometric consistency of the pose found."""


@dataclass
class Lap:
    """The time of one pass through a stage, milliseconds (set when the pass ends)."""

    wall_ms: float = 0.0
    cpu_ms: float = 0.0


class StageClock:
    """Accumulates wall and CPU milliseconds per stage.

    Args:
        stages: the stage names (default :data:`STAGES`, the localiser's).

    Attributes:
        wall_ms: stage -> wall milliseconds (0 for a stage never entered).
        cpu_ms: stage -> process CPU milliseconds.
    """

    def __init__(self, stages: tuple[str, ...] = STAGES) -> None:
        self.wall_ms = dict.fromkeys(stages, 0.0)
        self.cpu_ms = dict.fromkeys(stages, 0.0)

    @contextmanager
    def measure(self, stage: str) -> Iterator[Lap]:
        """Time the ``with`` block as one pass through ``stage``; yields its :class:`Lap`.

        Raises:
            KeyError: ``stage`` is not one of the clock's stages.
        """
        if stage not in self.wall_ms:
            raise KeyError(f"stage must be one of {tuple(self.wall_ms)}, got {stage!r}")
        lap = Lap()
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            yield lap
        finally:
            lap.wall_ms = 1000.0 * (time.perf_counter() - wall)
            lap.cpu_ms = 1000.0 * (time.process_time() - cpu)
            self.wall_ms[stage] += lap.wall_ms
            self.cpu_ms[stage] += lap.cpu_ms
