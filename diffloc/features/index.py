"""Exact nearest-neighbour search over global image descriptors by cosine similarity.

Descriptors are L2-normalised when the index is built and when it is queried, so cosine
similarity is a dot product. Two backends give the same neighbours:

- ``"matmul"``: one matrix product ``queries @ database.T`` and ``torch.topk`` (the default;
  fastest for the few thousand keyframes of a visual database);
- ``"kdtree"``: a ``scipy.spatial.cKDTree`` on the unit vectors, searched by Euclidean
  distance ``d``, with ``cosine = 1 - d^2 / 2``.

File format (one ``.npz``, loaded with ``allow_pickle=False``, written atomically): arrays
``descriptors`` (N, D) and ``ids`` (N,) int64, and ``metadata``, a 0-d unicode array holding
the JSON object ``{"format_version": 1, "kind": "diffloc-retrieval-index", "backend": ...,
"num_descriptors": N, "dim": D}``.
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

from diffloc.checks import ShapeError, check_finite, check_positive_int, check_shape
from diffloc.io.atomic import atomic_write_bytes
from diffloc.io.npz import read_npz_archive

__all__ = ["BACKENDS", "INDEX_FORMAT_VERSION", "INDEX_KIND", "RetrievalIndex"]

INDEX_FORMAT_VERSION = 1
INDEX_KIND = "diffloc-retrieval-index"
BACKENDS = ("matmul", "kdtree")
_ARRAYS = ("descriptors", "ids", "metadata")


def _check_backend(backend: str) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    return backend


class RetrievalIndex:
    """Top-k cosine search of query descriptors against a database of descriptors.

    Args:
        descriptors: (N, D) floating point database descriptors (normalised here; the dtype
            is kept, so float64 gives float64 scores).
        ids: (N,) int64 identifiers returned by :meth:`search_ids` (default ``0..N-1``).
        backend: ``"matmul"`` or ``"kdtree"``.

    Raises:
        ShapeError: ``descriptors`` is not (N, D) with N >= 1, or ``ids`` is not (N,).
        ValueError: non-finite descriptors, an unknown backend.

    Example:
        >>> index = RetrievalIndex(torch.randn(100, 16))
        >>> scores, indices = index.search(torch.randn(3, 16), k=5)
        >>> scores.shape, indices.shape
        (torch.Size([3, 5]), torch.Size([3, 5]))
    """

    def __init__(
        self,
        descriptors: torch.Tensor,
        ids: torch.Tensor | None = None,
        backend: str = "matmul",
    ) -> None:
        descriptors = torch.as_tensor(descriptors)
        check_shape(descriptors, "N,D", "descriptors")
        if descriptors.shape[0] == 0 or descriptors.shape[1] == 0:
            raise ShapeError(f"descriptors must be non-empty, got {tuple(descriptors.shape)}")
        if not descriptors.is_floating_point():
            raise TypeError(f"descriptors must be floating point, got {descriptors.dtype}")
        check_finite(descriptors, "descriptors")
        self.backend = _check_backend(backend)
        self.descriptors = F.normalize(descriptors.detach().cpu(), dim=1)
        n = self.descriptors.shape[0]
        if ids is None:
            ids = torch.arange(n, dtype=torch.int64)
        ids = torch.as_tensor(ids)
        check_shape(ids, f"{n}", "ids")
        self.ids = ids.to(torch.int64).cpu()
        self._tree: cKDTree | None = None

    def __len__(self) -> int:
        return self.descriptors.shape[0]

    @property
    def dim(self) -> int:
        """Descriptor dimension D."""
        return self.descriptors.shape[1]

    def _kdtree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.descriptors.to(torch.float64).numpy())
        return self._tree

    def search(self, queries: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The k most similar database descriptors of each query, best first.

        Args:
            queries: (Q, D) query descriptors (normalised here).
            k: neighbours per query; at most ``len(self)`` are returned.

        Returns:
            ``(scores (Q, k'), indices (Q, k'))`` with ``k' = min(k, N)``: cosine similarities
            (descending, in the database dtype) and int64 row indices into the database.

        Raises:
            ShapeError: ``queries`` is not (Q, D) with this index's D.
            ValueError: ``k`` is not a positive integer, non-finite queries.
        """
        k = min(check_positive_int(k, "k"), len(self))
        queries = torch.as_tensor(queries)
        check_shape(queries, f"Q,{self.dim}", "queries")
        check_finite(queries, "queries")
        queries = F.normalize(queries.detach().cpu().to(self.descriptors.dtype), dim=1)
        if self.backend == "matmul":
            scores, indices = torch.topk(queries @ self.descriptors.T, k, dim=1)
            return scores, indices
        distance, indices = self._kdtree().query(queries.to(torch.float64).numpy(), k=k)
        distance = np.asarray(distance).reshape(len(queries), k)
        indices = np.asarray(indices).reshape(len(queries), k)
        scores = torch.from_numpy(1.0 - 0.5 * distance**2).to(self.descriptors.dtype)
        return scores, torch.from_numpy(indices).to(torch.int64)

    def search_ids(self, queries: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Like :meth:`search` but returns ``ids`` (Q, k') instead of row indices."""
        scores, indices = self.search(queries, k)
        return scores, self.ids[indices]

    def save(self, path: str | os.PathLike) -> Path:
        """Write the index to ``path`` (an ``.npz`` file) atomically.

        Returns:
            ``path`` as a :class:`~pathlib.Path`.
        """
        path = Path(path)
        metadata = {
            "format_version": INDEX_FORMAT_VERSION,
            "kind": INDEX_KIND,
            "backend": self.backend,
            "num_descriptors": len(self),
            "dim": self.dim,
        }
        buffer = io.BytesIO()
        np.savez(
            buffer,
            descriptors=self.descriptors.numpy(),
            ids=self.ids.numpy(),
            metadata=np.array(json.dumps(metadata, sort_keys=True)),
        )
        atomic_write_bytes(path, buffer.getvalue())
        return path

    @classmethod
    def load(cls, path: str | os.PathLike, backend: str | None = None) -> RetrievalIndex:
        """Read an index written by :meth:`save`.

        Args:
            path: the ``.npz`` file.
            backend: override the saved backend (``None`` keeps it).

        Returns:
            The index, with bit-identical descriptors and ids.

        Raises:
            FileNotFoundError: ``path`` does not exist.
            ValueError: not an npz archive, missing or pickled arrays, foreign ``kind``,
                unknown ``format_version``, or arrays that contradict the metadata.
        """
        path = Path(path)
        arrays = _read_npz(path)
        metadata = _parse_metadata(path, arrays["metadata"])
        descriptors, ids = arrays["descriptors"], arrays["ids"]
        n, dim = metadata.get("num_descriptors"), metadata.get("dim")
        if descriptors.ndim != 2 or descriptors.shape != (n, dim):
            raise ValueError(
                f"{path}: descriptors have shape {descriptors.shape}, metadata says ({n}, {dim})"
            )
        if descriptors.dtype.kind != "f" or ids.shape != (n,) or ids.dtype != np.int64:
            raise ValueError(
                f"{path}: expected floating descriptors and ({n},) int64 ids, got "
                f"{descriptors.dtype} descriptors and {ids.shape} {ids.dtype} ids"
            )
        saved_backend = metadata.get("backend")
        if saved_backend not in BACKENDS:
            raise ValueError(f"{path}: unknown backend {saved_backend!r} in the metadata")
        index = cls.__new__(cls)
        index.backend = _check_backend(saved_backend if backend is None else backend)
        index.descriptors = torch.from_numpy(descriptors)
        index.ids = torch.from_numpy(ids)
        index._tree = None
        return index


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise FileNotFoundError(f"retrieval index not found: {path}")
    arrays = read_npz_archive(path)
    missing = [name for name in _ARRAYS if name not in arrays]
    if missing:
        raise ValueError(f"{path}: not a retrieval index (missing arrays {missing})")
    return {name: arrays[name] for name in _ARRAYS}


def _parse_metadata(path: Path, raw: np.ndarray) -> dict[str, Any]:
    if raw.shape != () or raw.dtype.kind != "U":
        raise ValueError(f"{path}: 'metadata' must be a JSON string")
    try:
        metadata = json.loads(str(raw))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: metadata is not valid JSON: {exc}") from exc
    if not isinstance(metadata, dict) or metadata.get("kind") != INDEX_KIND:
        kind = metadata.get("kind") if isinstance(metadata, dict) else None
        raise ValueError(f"{path}: 'kind' must be {INDEX_KIND!r}, got {kind!r}")
    version = metadata.get("format_version")
    if isinstance(version, bool) or version != INDEX_FORMAT_VERSION:
        raise ValueError(
            f"{path}: unknown format_version {version!r} (this reader knows {INDEX_FORMAT_VERSION})"
        )
    return metadata
