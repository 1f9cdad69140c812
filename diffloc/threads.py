"""Scoped control of torch's intra-op thread count."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

__all__ = ["intra_op_threads"]


@contextlib.contextmanager
def intra_op_threads(count: int | None) -> Iterator[None]:
    """Run the body with ``count`` torch intra-op threads, restoring the setting afterwards.

    Small tensor workloads (RANSAC hypotheses, a few hundred correspondences) run fastest on
    one thread: more threads only add synchronisation.

    Args:
        count: threads for the body, or ``None`` to leave torch's setting alone.

    Example:
        >>> with intra_op_threads(1):
        ...     torch.get_num_threads()
        1
    """
    previous = torch.get_num_threads()
    if count is None or count == previous:
        yield
        return
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
