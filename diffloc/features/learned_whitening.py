"""Learned discriminative whitening of global descriptors from matching pairs.

A global descriptor (e.g. NetVLAD) of two images of the same place differs by nuisance:
lighting, and for a rendered database the render / real-image gap. Given pairs known to show
the same place, a linear projection can damp the directions along which such pairs differ and
keep those along which the whole collection varies (Mikolajczyk & Matas 2007; used for CNN
retrieval by Radenovic et al. 2018). With ``x`` the descriptors, ``m`` their mean:

1. PCA-whitening to ``pca_dim`` dimensions, ``y = P0^T (x - m)`` (the pair covariance below
   needs fewer dimensions than pairs);
2. the covariance of the pair differences, ``C_S = mean_(i,j) (y_i - y_j)(y_i - y_j)^T``, shrunk
   towards its mean variance (``(1 - s) C_S + s tr(C_S) / d I``) so few pairs stay
   well-conditioned, and ``P1 = C_S^(-1/2)`` (eigenvalues floored at :data:`EIGEN_FLOOR` of
   the largest): the matching pairs' differences become white;
3. PCA of the ``P1``-projected descriptors, keeping the ``dim`` axes of largest variance
   (``P2``): of what is left, what separates places.

The projection is ``P = P0 P1 P2`` (G, dim): a descriptor maps to ``normalise(P^T (x - m))``.
No pair's label is needed beyond "same place"; negatives are implicitly every other image.

Usage::

    mean, projection = learned_whitening(descriptors, pairs, dim=256)
    whitened = F.normalize((descriptors - mean) @ projection, dim=1)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from diffloc.checks import ShapeError, check_positive_int, check_shape

__all__ = ["EIGEN_FLOOR", "LearnedWhiteningConfig", "learned_whitening"]


@dataclass
class LearnedWhiteningConfig:
    """Settings of :func:`learned_whitening`.

    Attributes:
        dim: output dimension.
        pca_dim: dimension of the first PCA-whitening (``None``: ``dim``).
        shrinkage: share of the pair covariance replaced by its mean variance.
    """

    dim: int = 256
    pca_dim: int | None = 256
    shrinkage: float = 0.1

    def __post_init__(self) -> None:
        check_positive_int(self.dim, "dim")
        if self.pca_dim is not None:
            check_positive_int(self.pca_dim, "pca_dim")
            if self.pca_dim < self.dim:
                raise ValueError(f"pca_dim ({self.pca_dim}) must be >= dim ({self.dim})")
        if not 0.0 <= self.shrinkage <= 1.0:
            raise ValueError(f"shrinkage must be in [0, 1], got {self.shrinkage!r}")


EIGEN_FLOOR = 1e-6
"""Eigenvalues of the pair covariance below this share of the largest are raised to it: a
direction in which no pair differs (fewer pairs than dimensions, no shrinkage) is amplified
1000x at most rather than without bound."""


def _inverse_sqrt(matrix: torch.Tensor) -> torch.Tensor:
    """``matrix^(-1/2)`` of a symmetric positive semi-definite (d, d) matrix, eigenvalues
    floored at :data:`EIGEN_FLOOR` of the largest."""
    values, vectors = torch.linalg.eigh(matrix)
    values = values.clamp_min(EIGEN_FLOOR * values.max())
    return (vectors * values.rsqrt()) @ vectors.T


def learned_whitening(
    descriptors: torch.Tensor,
    pairs: torch.Tensor,
    dim: int,
    pca_dim: int | None = None,
    shrinkage: float = 0.1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and projection of the learned whitening of ``descriptors`` (module docstring).

    Args:
        descriptors: (N, G) global descriptors of every image (both sides of the pairs and
            any others, which shape the final PCA).
        pairs: (P, 2) int64 indices into ``descriptors`` of images showing the same place.
        dim: output dimension, ``dim <= pca_dim``.
        pca_dim: dimension of the first PCA-whitening (``None``: ``dim``); at most
            ``min(N - 1, G)``.
        shrinkage: ``s`` in [0, 1], the share of the pair covariance replaced by its mean
            variance.

    Returns:
        ``(mean (G,), projection (G, dim))`` float32.

    Raises:
        ShapeError: ``descriptors`` not (N, G) or ``pairs`` not (P, 2).
        ValueError: no pair, a pair index out of range, non-finite descriptors, dimensions
            out of range, or ``shrinkage`` outside [0, 1].

    Example (two places, each seen twice with a nuisance along the first axis):
        >>> x = torch.tensor([[1.0, 1.0, 0.0], [-1.0, 1.0, 0.0],
        ...                   [1.0, -1.0, 0.0], [-1.0, -1.0, 0.0]])
        >>> x = x + 0.01 * torch.randn(4, 3, generator=torch.Generator().manual_seed(0))
        >>> mean, P = learned_whitening(x, torch.tensor([[0, 1], [2, 3]]), dim=1, pca_dim=2)
        >>> y = (x - mean) @ P  # the nuisance axis is gone: pairs agree, places differ
        >>> bool((y[0] * y[1] > 0) and (y[0] * y[2] < 0))
        True
    """
    check_shape(descriptors, "N,G", "descriptors")
    check_shape(pairs, "P,2", "pairs")
    n, g = descriptors.shape
    pca_dim = dim if pca_dim is None else pca_dim
    check_positive_int(dim, "dim")
    check_positive_int(pca_dim, "pca_dim")
    if not dim <= pca_dim <= min(n - 1, g):
        raise ValueError(
            f"need dim <= pca_dim <= min(N - 1, G) = {min(n - 1, g)}, got dim {dim}, "
            f"pca_dim {pca_dim}"
        )
    if not 0.0 <= shrinkage <= 1.0:
        raise ValueError(f"shrinkage must be in [0, 1], got {shrinkage!r}")
    if len(pairs) == 0:
        raise ValueError("learned whitening needs at least one pair of the same place")
    if pairs.dtype != torch.int64 or bool(((pairs < 0) | (pairs >= n)).any()):
        raise ValueError(f"pairs must be int64 indices in [0, {n})")
    x = descriptors.detach().to(torch.float64)
    if not bool(torch.isfinite(x).all()):
        raise ValueError("descriptors must be finite")
    mean = x.mean(0)
    _, singular, vh = torch.linalg.svd(x - mean, full_matrices=False)
    variance = singular[:pca_dim] ** 2 / (n - 1)
    if bool((variance <= 0).any()):
        raise ShapeError(f"the descriptors span fewer than pca_dim = {pca_dim} dimensions")
    pca = vh[:pca_dim].T / variance.sqrt()  # (G, pca_dim)
    y = (x - mean) @ pca
    difference = y[pairs[:, 0]] - y[pairs[:, 1]]
    pair_cov = difference.T @ difference / len(difference)
    spread = pair_cov.diagonal().mean()
    pair_cov = (1.0 - shrinkage) * pair_cov + shrinkage * spread * torch.eye(
        pca_dim, dtype=torch.float64
    )
    damp = _inverse_sqrt(pair_cov)
    z = y @ damp
    z = z - z.mean(0)
    values, vectors = torch.linalg.eigh(z.T @ z / n)
    keep = vectors[:, torch.argsort(values, descending=True)[:dim]]
    return mean.float(), (pca @ damp @ keep).float()
