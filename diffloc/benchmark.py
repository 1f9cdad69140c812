"""Timing and memory helpers shared by the benchmark scripts in ``experiments/``."""

from __future__ import annotations

import ctypes
import ctypes.util
import statistics
import time
from collections.abc import Callable
from pathlib import Path

__all__ = ["median_ms", "peak_added_mb", "peak_rss_mb", "retain_freed_heap"]


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


def _glibc_function(name: str) -> Callable[..., int] | None:
    """A function of the C library when it is glibc's (it has ``name``), else ``None``."""
    library = ctypes.util.find_library("c")
    return getattr(ctypes.CDLL(library), name, None) if library else None


def _release_free_heap() -> None:
    """Give the heap memory that is free but still resident back to the system (glibc's
    ``malloc_trim``; nothing elsewhere)."""
    malloc_trim = _glibc_function("malloc_trim")
    if malloc_trim is not None:
        malloc_trim(0)


M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
"""glibc ``mallopt`` parameter numbers (``malloc.h``)."""


def retain_freed_heap(mmap_threshold_mb: int = 32, trim_threshold_mb: int = 1024) -> bool:
    """Keep freed tensor memory in this process for reuse instead of unmapping it (glibc).

    glibc serves allocations from ``mmap_threshold_mb`` MB up by fresh ``mmap`` pages and
    hands them back on free; smaller ones come from the heap, whose free top is given back once
    it exceeds ``trim_threshold_mb``. By default both thresholds start low (128 kB) and float,
    so a loop of large temporaries (a 640x480 mesh render's buffers of 1-15 MB) touches fresh
    pages every time: ~9 300 page faults per render and a sixth of its CPU time here
    (``experiments/bench_mesh_render.py``). Raising both makes later iterations reuse the
    memory; the process then keeps up to ``trim_threshold_mb`` MB of freed memory resident.
    Process-wide: call it once at start-up, from a script that wants it, never from library
    code.

    Args:
        mmap_threshold_mb: allocations below this many MB come from the heap (glibc caps it at
            32 on 64-bit systems).
        trim_threshold_mb: free heap kept before any is given back.

    Returns:
        Whether glibc took both settings (``False`` on another C library).
    """
    mallopt = _glibc_function("mallopt")
    if mallopt is None:
        return False
    mmap_ok = mallopt(M_MMAP_THRESHOLD, mmap_threshold_mb << 20)
    trim_ok = mallopt(M_TRIM_THRESHOLD, trim_threshold_mb << 20)
    return bool(mmap_ok and trim_ok)


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
