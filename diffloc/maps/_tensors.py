"""Validation and indexing shared by the map dataclasses (fields of per-point tensors)."""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

import numpy as np
import torch

from diffloc.checks import ShapeError, check_finite, check_shape

UNIT_NORMAL_TOLERANCE = 1e-3
"""Largest accepted ``| |n| - 1 |`` for a normal to count as a unit vector."""

T = TypeVar("T", bound="PerPointFields")


def as_float32(x: Any, spec: str, name: str) -> torch.Tensor:
    """A finite float32 tensor of shape ``spec`` from a floating tensor or array.

    Args:
        x: a floating-point ``torch.Tensor`` or ``np.ndarray``.
        spec: the expected shape, as for :func:`diffloc.checks.check_shape` (e.g. ``"N,3"``).
        name: the field name used in error messages.

    Returns:
        ``x`` as a float32 tensor (on its device; a numpy array becomes a CPU tensor).

    Raises:
        TypeError: not a tensor or array, or not floating point.
        ShapeError: the shape does not match ``spec``.
        ValueError: NaN or infinite values.
    """
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(np.ascontiguousarray(x))
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor or numpy array, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must hold floating-point values, got dtype {x.dtype}")
    check_shape(x, spec, name)
    x = x.to(torch.float32)
    check_finite(x, name)
    return x


def check_unit_vectors(x: torch.Tensor, name: str) -> None:
    """Raise ``ValueError`` unless every row of ``x`` (N, 3) has norm 1 (within tolerance)."""
    error = (torch.linalg.vector_norm(x.double(), dim=-1) - 1.0).abs()
    bad = error > UNIT_NORMAL_TOLERANCE
    if bool(bad.any()):
        first = int(bad.nonzero()[0, 0])
        raise ValueError(
            f"{name} must be unit vectors (| |n| - 1 | <= {UNIT_NORMAL_TOLERANCE}); "
            f"{int(bad.sum())} are not, e.g. row {first} has norm {1.0 + float(error[first]):.6g}"
        )


def check_in_range(x: torch.Tensor, low: float, high: float, name: str) -> None:
    """Raise ``ValueError`` unless every value of ``x`` lies in ``[low, high]``."""
    if x.numel() and bool(((x < low) | (x > high)).any()):
        raise ValueError(
            f"{name} must lie in [{low}, {high}], got values in "
            f"[{float(x.min()):.6g}, {float(x.max()):.6g}]"
        )


class PerPointFields:
    """Mixin for frozen dataclasses whose fields are all (N, ...) tensors or ``None``.

    The first field defines ``N``. Subclasses validate their fields in ``__post_init__``;
    :meth:`select` and :meth:`to` build a new instance, so the result is validated again.
    """

    def _tensors(self) -> dict[str, torch.Tensor | None]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def __len__(self) -> int:
        """Number of points ``N``."""
        return int(next(iter(self._tensors().values())).shape[0])

    def _check_same_device(self) -> None:
        devices = {name: t.device for name, t in self._tensors().items() if t is not None}
        if len(set(devices.values())) > 1:
            raise ValueError(f"all fields must be on one device, got {devices}")

    def select(self: T, index: torch.Tensor | np.ndarray | list[int] | slice) -> T:
        """The points picked by a mask or an index, in the order of ``index``.

        Args:
            index: an (N,) bool mask (tensor or array), a (K,) integer index (tensor, array
                or list of ints; repeats allowed) or a ``slice``.

        Returns:
            A new instance with ``K`` points (a slice gives views of this map's tensors).

        Raises:
            ShapeError: a bool mask whose length is not ``N``, or an index that is not 1-D.
            TypeError: an index that is neither bool nor integer.
            IndexError: integer indices out of range.
        """
        fields = self._tensors()
        device = next(iter(fields.values())).device
        if not isinstance(index, slice):
            if isinstance(index, list):
                index = torch.as_tensor(index, dtype=torch.long)
            index = torch.as_tensor(index).to(device)
            if index.dtype == torch.bool:
                check_shape(index, str(len(self)), "mask")
            elif index.is_floating_point() or index.is_complex():
                raise TypeError(f"index must be a bool mask or integers, got dtype {index.dtype}")
            elif index.dim() != 1:
                raise ShapeError(f"index must be 1-D, got shape {tuple(index.shape)}")
        picked = {name: None if t is None else t[index] for name, t in fields.items()}
        return dataclasses.replace(self, **picked)

    def to(self: T, device: torch.device | str) -> T:
        """A copy with every tensor on ``device`` (dtypes unchanged)."""
        moved = {n: None if t is None else t.to(device) for n, t in self._tensors().items()}
        return dataclasses.replace(self, **moved)
