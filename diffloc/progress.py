"""Progress bars that stay quiet in CI."""

from __future__ import annotations

import os
from collections.abc import Iterable
from typing import TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")


def progress_enabled(requested: bool = True) -> bool:
    """True if progress bars were requested and the environment is not CI (``CI=true``)."""
    return requested and os.environ.get("CI", "").strip().lower() not in {"true", "1", "yes"}


def progress(items: Iterable[T], description: str, enabled: bool = True, total: int | None = None):
    """Wrap ``items`` in a tqdm bar unless disabled or running in CI."""
    return tqdm(items, desc=description, total=total, disable=not progress_enabled(enabled))
