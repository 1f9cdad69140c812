"""Value checks shared by the layout configs of the procedural worlds."""

from __future__ import annotations

from typing import Any

import numpy as np


def _check_config(cfg: Any, positive: tuple[str, ...], counts: tuple[str, ...]) -> None:
    for name in positive:
        value = getattr(cfg, name)
        if not isinstance(value, int | float) or isinstance(value, bool) or not value > 0:
            raise ValueError(f"layout.{name} must be a positive number, got {value!r}")
    for name in counts:
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
            raise ValueError(f"layout.{name} must be a non-negative integer, got {value!r}")
    size = cfg.texture_size
    if isinstance(size, bool) or not isinstance(size, int | np.integer) or size < 16:
        raise ValueError(f"layout.texture_size must be an integer >= 16, got {size!r}")
