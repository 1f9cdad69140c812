"""Timing and memory helpers shared by the benchmark scripts in ``experiments/``."""

from __future__ import annotations

import ctypes
import ctypes.util
import statistics
import time
from collections.abc import Callable
from pathlib import Path

__all__ = ["median_ms", "peak_added_mb", "peak_rss_mb"]


def median_ms(function: Callable[[], object], repeats: int, warm_up: bool = True) -> float:
    """Median wall time of ``function()`` in milliseconds, after one warm-up call if asked.

    Example:
        >>> median_ms(lambda: sum(range(1000)), repeats=5) >= 0
        True
    """
    if warm_up:
        function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append((time.perf_counter() - start) * 1e3)
    return round(statistics.median(times), 3)


def _status_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (``VmHWM``), in MB (Linux only)."""
    return round(_status_kb("VmHWM") / 1024, 1)


def _release_free_heap() -> None:
    """Give the heap memory that is free but still resident back to the system (glibc's
    ``malloc_trim``; nothing elsewhere)."""
    name = ctypes.util.find_library("c")
    malloc_trim = getattr(ctypes.CDLL(name), "malloc_trim", None) if name else None
    if malloc_trim is not None:
        malloc_trim(0)


def peak_added_mb(function: Callable[[], object]) -> float:
    """Peak resident memory added while ``function()`` runs, in MB (Linux only).

    Returns freed heap memory to the system and resets the process's peak (``VmHWM``)
    through ``/proc/self/clear_refs`` first, so the figure is the memory this call needs on
    top of what was in use before it (without the trim, temporaries that fit in memory that
    earlier calls freed but the allocator kept would count as nothing).
    """
    _release_free_heap()
    Path("/proc/self/clear_refs").write_text("5")
    before = _status_kb("VmRSS")
    function()
    return round((_status_kb("VmHWM") - before) / 1024, 1)
