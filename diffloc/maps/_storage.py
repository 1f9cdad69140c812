"""File formats shared by the maps: versioned ``.npz`` archives and exact PLY colours.

``.npz`` archives hold one array per field plus ``format_version`` (int64 scalar) and ``kind``
(a string naming the map type); they are written atomically and read with
``allow_pickle=False``. PLY stores colours twice: as ``uchar red, green, blue`` for viewers and
as float32 ``red_f32, green_f32, blue_f32`` so that float colours read back bit-exactly.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from diffloc.io.atomic import atomic_open
from diffloc.io.npz import read_npz_archive
from diffloc.io.ply import PointCloudData

EXACT_COLOR_PROPERTIES = ("red_f32", "green_f32", "blue_f32")
"""PLY vertex properties holding the float32 colour channels."""


def map_suffix(path: str | os.PathLike) -> str:
    """The lower-case suffix of a map file, ``".ply"`` or ``".npz"``; ``ValueError`` otherwise."""
    suffix = Path(path).suffix.lower()
    if suffix not in (".ply", ".npz"):
        raise ValueError(f"{path}: unknown map file type {suffix!r} (use .ply or .npz)")
    return suffix


def write_npz(
    path: str | os.PathLike, kind: str, version: int, fields: dict[str, torch.Tensor | None]
) -> None:
    """Write the non-``None`` fields, ``kind`` and ``format_version`` to ``path`` atomically.

    Args:
        path: destination ``.npz`` file.
        kind: the map type, e.g. ``"diffloc-surfel-map"``.
        version: the format version written as ``format_version``.
        fields: name -> tensor (stored as numpy arrays with the tensor's dtype) or ``None``.
    """
    arrays = {n: t.detach().cpu().numpy() for n, t in fields.items() if t is not None}
    with atomic_open(path, "wb") as handle:
        np.savez(handle, format_version=np.array(version, np.int64), kind=np.array(kind), **arrays)


def read_npz(
    path: str | os.PathLike,
    kind: str,
    version: int,
    required: tuple[str, ...],
    optional: tuple[str, ...] = (),
) -> dict[str, np.ndarray]:
    """Read an archive written by :func:`write_npz` and check its kind, version and keys.

    Args:
        path: the ``.npz`` file.
        kind: the expected ``kind`` entry.
        version: the supported ``format_version``.
        required: field names that must be present.
        optional: field names that may be present.

    Returns:
        Field name -> float32 array, for the required and the present optional fields.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: unreadable or truncated archive, pickled content, missing or unknown
            entries, another kind or version, or a field that is not float32. The message
            names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"map file not found: {path}")
    arrays = read_npz_archive(path)
    if "format_version" not in arrays or "kind" not in arrays:
        raise ValueError(
            f"{path}: no 'format_version'/'kind' entries, so not a diffloc {kind} file "
            f"(entries: {sorted(arrays)})"
        )
    found_kind, found_version = arrays.pop("kind"), arrays.pop("format_version")
    if found_kind.shape != () or found_kind.dtype.kind != "U" or str(found_kind) != kind:
        raise ValueError(f"{path}: holds {found_kind!s:.60}, expected a {kind}")
    if found_version.shape != () or found_version.dtype.kind not in "iu":
        raise ValueError(f"{path}: format_version must be an integer scalar")
    if int(found_version) != version:
        raise ValueError(
            f"{path}: format_version {int(found_version)} is not supported (expected {version})"
        )
    missing = [name for name in required if name not in arrays]
    unknown = sorted(set(arrays) - set(required) - set(optional))
    if missing or unknown:
        raise ValueError(f"{path}: missing entries {missing}, unknown entries {unknown}")
    for name, array in arrays.items():
        if array.dtype != np.float32:
            raise ValueError(f"{path}: entry {name!r} must be float32, got {array.dtype}")
    return arrays


def exact_color_columns(colors: torch.Tensor | None) -> dict[str, np.ndarray]:
    """The float32 colour channels as PLY vertex properties (empty for ``None``).

    Args:
        colors: (N, 3) float32 colours in [0, 1], or ``None``.

    Returns:
        ``{"red_f32": (N,), "green_f32": (N,), "blue_f32": (N,)}`` or ``{}``.
    """
    if colors is None:
        return {}
    array = colors.detach().cpu().numpy()
    return {
        name: np.ascontiguousarray(array[:, i]) for i, name in enumerate(EXACT_COLOR_PROPERTIES)
    }


def colors_from_ply(cloud: PointCloudData) -> np.ndarray | None:
    """(N, 3) colours of a PLY point cloud: the exact float32 columns, else ``red green blue``.

    Args:
        cloud: the cloud read by :func:`diffloc.io.ply.read_point_cloud`.

    Returns:
        (N, 3) colours in [0, 1] or ``None`` when the file has no colours.
    """
    if all(name in cloud.extra for name in EXACT_COLOR_PROPERTIES):
        return np.stack([cloud.extra[name] for name in EXACT_COLOR_PROPERTIES], axis=1)
    return cloud.colors


@contextlib.contextmanager
def naming_file(path: str | os.PathLike, what: str) -> Iterator[None]:
    """Turn ``ValueError``/``TypeError`` raised while building a map into one naming ``path``.

    Args:
        path: the file being loaded.
        what: what the file should hold, e.g. ``"surfel map"``.
    """
    try:
        yield
    except (ValueError, TypeError) as exc:
        if str(path) in str(exc):
            raise
        raise ValueError(f"{path}: not a valid {what}: {exc}") from exc
